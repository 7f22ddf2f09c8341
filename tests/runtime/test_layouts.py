"""The splat, footprint and walk-state layouts are named once (qr_cl.runtime.constants) and the
kernels follow the names: a splat built from named fields comes back from project.cl field by
field, and so it does when the build is given another layout; selections and fused V-Render
images walked in windows keep their bytes when the walk states are given other layouts."""
import numpy as np

from qr_cl.render import rasterize_plan
from qr_cl.runtime import (ALPHA_MIN, FOOTPRINT_INTS, FOOTPRINT_RECT, KERNEL_CONSTANTS, SAMPLERS, SPLAT, SPLAT_FLOATS,
                           VOLUME_STATE, VOLUME_STATE_FLOATS, WALK_STATE, WALK_STATE_FLOATS, WALK_STATE_INTS, Runtime,
                           SplatLayout, VolumeStateLayout, WalkStateLayout, channel_layout, context, device_empty,
                           padded_rows, runtime, to_device)
from qr_cl.stages import project_ref, render_fused, select
from qr_cl.stages.project import lane_items, project, tile_grid
from tests.twins import H, W, origin_camera

#: Every field in other slots than SPLAT's; absgrad on the slots of depth and sigma_max again.
MOVED = SplatLayout(mean=slice(6, 8), conic=slice(3, 6), opacity=2, depth=0, sigma_max=1, absgrad=slice(0, 2))
#: Every field of the walk state in other slots than WALK_STATE's.
MOVED_WALK = WalkStateLayout(t=7, tq=3, mu=6, sigma=0, t_end=4, sum=1, sum_sq=5, used=2, k=3, n=0, done=1)
#: Every field of the fused V-Render's state in other slots than VOLUME_STATE's.
MOVED_VOLUME = VolumeStateLayout(t=3, depth_sum=0, done=1)


def _scene(n: int = 40, seed: int = 0):
    """n Gaussians in front of the origin camera (all visible), turned and stretched apart."""
    rng = np.random.default_rng(seed)
    means = np.stack([rng.uniform(-1, 1, n), rng.uniform(-0.7, 0.7, n), rng.uniform(2, 6, n)], 1)
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales = rng.uniform(0.02, 0.2, (n, 3))
    opacities = rng.uniform(0.1, 0.95, n)
    return [a.astype(np.float32) for a in (means, quats, scales, opacities)]


def _splats_from_fields(fields: dict[str, np.ndarray], layout: SplatLayout) -> np.ndarray:
    """[N, 8] splats holding ``fields`` (by SplatLayout field name) in the slots of ``layout``."""
    splats = np.zeros((len(fields["depth"]), SPLAT_FLOATS))
    for name, values in fields.items():
        splats[:, getattr(layout, name)] = values
    return splats


def _project(layout: SplatLayout, gaussians, cam):
    """project.cl built with ``layout``'s defines: (splats [N,8], footprints [N,16]) on the host."""
    rt = runtime()
    n = len(gaussians[0])
    tiles_x, tiles_y = tile_grid(W, H)
    out = {"splats": device_empty(rt, (n, SPLAT_FLOATS)), "radii": device_empty(rt, (n, 2), np.int32),
           "footprints": device_empty(rt, (n, FOOTPRINT_INTS), np.int32),
           "tiles_touched": device_empty(rt, n, np.int32), "depth_keys": device_empty(rt, n, np.int32)}
    means, quats, scales, opacities = (to_device(rt, a) for a in gaussians)
    rt.launch("project", lane_items(n), defines=layout.defines(), local_size=(16,), n=n, means=means,
              quats=quats, scales=scales, opacities=opacities,
              viewmat=to_device(rt, cam.viewmat.reshape(16)), fx=cam.K[0, 0], fy=cam.K[1, 1], cx=cam.K[0, 2],
              cy=cam.K[1, 2], width=W, height=H, near=0.01, far=1e10, tiles_x=tiles_x, tiles_y=tiles_y, **out)
    return out, out["splats"].get(), out["footprints"].get()


def test_layout_names_every_slot_once():
    """The splat's fields take the 8 slots once each; absgrad (of a gradient) those of depth and
    sigma_max, which a gradient has no other use for."""
    slots = [k for name, where in SPLAT._asdict().items() if name != "absgrad"
             for k in (range(SPLAT_FLOATS)[where] if isinstance(where, slice) else [where])]
    assert sorted(slots) == list(range(SPLAT_FLOATS))
    assert list(range(SPLAT_FLOATS)[SPLAT.absgrad]) == [SPLAT.depth, SPLAT.sigma_max]
    assert SPLAT.defines()["SPLAT_OPACITY"] == f"s{SPLAT.opacity:x}"


def test_splat_from_named_fields_round_trips_project():
    """project.cl's splats equal the splats built from the float64 twin's fields by name, and each
    field read back by name is the twin's; the footprint's rectangle is the twin's."""
    gaussians, cam = _scene(), origin_camera()
    twin = project_ref.project(*gaussians, cam.viewmat, cam.K, W, H)
    assert (twin["radii"][:, 0] > 0).all()
    fields = {"mean": twin["means2d"], "conic": twin["conics"], "opacity": twin["opacities"],
              "depth": twin["depths"], "sigma_max": np.log(twin["opacities"] / ALPHA_MIN)}
    expect = _splats_from_fields(fields, SPLAT)
    proj = project(runtime(), *(to_device(runtime(), a) for a in gaussians), cam.viewmat, cam.K, W, H, 0.01, 1e10)
    got = proj.splats.get()
    np.testing.assert_allclose(got, expect, rtol=1e-4, atol=1e-6)
    for name, values in fields.items():
        np.testing.assert_allclose(got[:, getattr(SPLAT, name)], values, rtol=1e-4, atol=1e-6, err_msg=name)
    np.testing.assert_array_equal(proj.footprints.get()[:, FOOTPRINT_RECT], twin["rects"])


def test_kernels_follow_another_layout():
    """project.cl and binning.cl's emit_keys built with MOVED: every field read by MOVED's names is
    the same bytes as read by SPLAT's from the default build, the footprints and sort keys too."""
    gaussians, cam = _scene(seed=1), origin_camera()
    runs = []
    for layout in (SPLAT, MOVED):
        dev, splats, footprints = _project(layout, gaussians, cam)
        touched = dev["tiles_touched"].get()
        n, m = len(touched), int(touched.sum())
        keys, values = device_empty(runtime(), m, np.uint64), device_empty(runtime(), m, np.int32)
        runtime().launch("emit_keys", n, defines=layout.defines(), n=n, footprints=dev["footprints"],
                         offsets=to_device(runtime(), np.cumsum(touched) - touched, np.int32), splats=dev["splats"],
                         tiles_x=tile_grid(W, H)[0], keys=keys, values=values)
        fields = {name: splats[:, getattr(layout, name)] for name in SPLAT._fields if name != "absgrad"}
        runs.append((splats, fields, footprints, keys.get(), values.get()))
    (splats, fields, footprints, keys, values), moved = runs
    assert m > len(touched) and not np.array_equal(moved[0], splats), "the layout moved the slots"
    for name, want in fields.items():
        np.testing.assert_array_equal(moved[1][name], want, err_msg=name)
    for name, got, want in zip(("footprints", "keys", "values"), moved[2:], (footprints, keys, values)):
        np.testing.assert_array_equal(got, want, err_msg=name)


def test_walk_state_names_every_slot_once():
    """The walk state's float fields take the 8 slots of its float8 once each, its int fields
    (INTS) slots of its int4 once each: one slot per field, whatever the sampler."""
    for layout in (WALK_STATE, MOVED_WALK):
        floats = [slot for name, slot in layout._asdict().items() if name not in WalkStateLayout.INTS]
        ints = [getattr(layout, name) for name in WalkStateLayout.INTS]
        assert sorted(floats) == list(range(WALK_STATE_FLOATS))
        assert len(set(ints)) == len(ints) and set(ints) <= set(range(WALK_STATE_INTS))
    assert WALK_STATE.defines()["WALK_TQ"] == f"s{WALK_STATE.tq:x}"


def _selections(rt: Runtime, scene, pixels) -> dict[str, np.ndarray]:
    """Every sampler's selection (K = 6) of the whole image and of ``pixels`` on ``rt``, by name."""
    m, q, s, o, v, K, w, h = scene
    plan = rasterize_plan(m, q, s, o, v, K, w, h, rt=rt)
    out = {}
    for sampler in SAMPLERS:
        for px in (None, pixels):
            for name, a in select(plan, sampler, 6, px).host().items():
                out[f"{sampler}/{px is None}/{name}"] = a
    return out


def _windowed_runtime(monkeypatch, defines: dict[str, str]) -> tuple[Runtime, list[str]]:
    """A runtime whose programs are built with ``defines`` over the kernel constants and whose
    walks end every 64 iterations (walk windows), and the list the names of the launches that
    resumed a walk are appended to."""
    monkeypatch.setattr(context, "KERNEL_CONSTANTS", {**KERNEL_CONSTANTS, **defines})
    rt = Runtime(runtime().device)
    rt.loop_limit = 64
    resumed = []
    launch = Runtime.launch

    def counted(self, name, *args, walk_from=None, **kwargs):
        if walk_from:
            resumed.append(name)
        launch(self, name, *args, **({} if walk_from is None else {"walk_from": walk_from}), **kwargs)
    monkeypatch.setattr(Runtime, "launch", counted)
    return rt, resumed


def test_selections_follow_another_walk_state_layout(random_scene, monkeypatch):
    """Selections walked in windows (block and tile walks) by kernels built with MOVED_WALK are
    the bytes of the default build's walks in one launch, and the walks did resume."""
    pixels = np.random.default_rng(5).integers(0, random_scene[6:], (90, 2))
    want = _selections(runtime(), random_scene, pixels)
    rt, resumed = _windowed_runtime(monkeypatch, MOVED_WALK.defines())
    for gpu in (False, True):
        rt.gpu_shaped = gpu
        resumed.clear()
        got = _selections(rt, random_scene, pixels)
        assert {"tile_quantile" if gpu else "select_quantile", "tile_stratified" if gpu else "select_stratified"} \
            <= set(resumed), resumed
        assert [k for k in want if want[k].tobytes() != got[k].tobytes()] == [], gpu


def test_volume_state_names_every_slot_once():
    for layout in (VOLUME_STATE, MOVED_VOLUME):
        assert len(set(layout)) == len(layout) and set(layout) <= set(range(VOLUME_STATE_FLOATS))
    assert VOLUME_STATE.defines()["VSTATE_DEPTH_SUM"] == f"s{VOLUME_STATE.depth_sum:x}"


def _fused(rt: Runtime, scene, channels: int = 5) -> list[np.ndarray]:
    """The fused V-Render's image, alpha and depth of ``scene`` with seeded features, on ``rt``."""
    m, q, s, o, v, K, w, h = scene
    plan = rasterize_plan(m, q, s, o, v, K, w, h, rt=rt)
    feats = np.random.default_rng(2).random((len(m), channels)).astype(np.float32)
    table = to_device(rt, padded_rows(feats, channel_layout(channels, rt.gpu_shaped)[2]))
    return [a.copy() for a in render_fused(plan, table, channels)]


def test_fused_vrender_follows_another_volume_state_layout(random_scene, monkeypatch):
    """The fused V-Render walked in windows (block and tile walks) by kernels built with
    MOVED_VOLUME gives the bytes of the default build's walk in one launch, and it did resume."""
    base = Runtime(runtime().device)
    want = {}
    for gpu in (False, True):
        base.gpu_shaped = gpu
        want[gpu] = _fused(base, random_scene)
    rt, resumed = _windowed_runtime(monkeypatch, MOVED_VOLUME.defines())
    for gpu in (False, True):
        rt.gpu_shaped = gpu
        resumed.clear()
        got = _fused(rt, random_scene)
        assert ("tile_vrender" if gpu else "vrender") in resumed, resumed
        assert [i for i, (a, b) in enumerate(zip(want[gpu], got)) if a.tobytes() != b.tobytes()] == [], gpu
