"""The budget of a reproduction (:class:`Plan`, :data:`PLANS`: "full", "quick" and "smoke") and the
training runs it compares (:class:`TrainingRun`: a renderer, its K, opacity noise and seed)."""
from __future__ import annotations

from dataclasses import dataclass, field

from ...runtime import DEFAULTS

NOISE_K = DEFAULTS.k                  # the noise table's Q-Render K (paper: "Sensitivity under Gaussian Perturbation")

LABELS = {"volume": "V-Render", "quantile": "Q-Render", "topk": "top-K", "stratified": "Stratified-K"}


@dataclass
class Plan:
    """The budget of one reproduction: rooms (``room``: SyntheticConfig overrides of the "3dgs"
    style), training (same ``steps``, ``views`` and ``rays`` for every renderer and for GS-Net
    overfit to the held-out room, each run repeated with ``seeds`` seeds), the K values and noise
    scales, the sizes of the timing, profile and RGB measurements (pixels), the flat room compared
    with them (``flat_room``: overrides of the default flat room, the demo's), top-K's K values
    (``topk_ks``; None: ``ks``), Dr.Splat's K, and
    the rooms with the depth structure where top-K fails and its K there (``depth_room``:
    SyntheticConfig overrides, empty for none; :mod:`qr_cl.app.experiments.depth_rooms`)."""

    train_rooms: int
    steps: int
    ks: tuple[int, ...]
    stratified_ks: tuple[int, ...]
    noise: tuple[float, ...]
    room: dict = field(default_factory=dict)
    seeds: int = 3
    views: int = 4
    rays: int = 2048
    timing_views: int = 2
    timing_size: tuple[int, int] = (640, 480)
    timing_rounds: int = 3
    rgb_ks: tuple[int, ...] = (10, 20, 40)
    rgb_views: int = 4
    rgb_size: tuple[int, int] = (640, 480)
    profile_k: int = 10
    topk_ks: tuple[int, ...] | None = None
    stats_views: int = 4
    dense_gaussians: int = 300_000
    flat_room: dict = field(default_factory=dict)
    drsplat_k: int = 40
    depth_room: dict = field(default_factory=dict)
    depth_k: int = 5


#: SyntheticConfig overrides of rooms whose rays have the depth structure where top-K fails: each
#: surface a 5 cm shell of 8 faint layers (Beta(1, 3) opacities), so a ray's weight decays through it.
DEPTH_ROOM = {"layers": 8.0, "thickness": 0.05, "opacity_beta": (1.0, 3.0)}

#: The quick plan's budget, chosen by measurement (``bench/quick_budget.py``, reports in
#: bench/reports/quick-budget-xeon-2cores): with 2 or 4 training rooms GS-Net learns walls, floors and a
#: few furniture classes and then fits the training rooms; with 12 it learns cabinets, chairs and
#: tables by 300 steps, and 600 steps or 24 rooms gain nothing more.
PLANS = {
    "full": Plan(train_rooms=12, steps=300, ks=(5, 10, 20, 40, 50), stratified_ks=(10, 40),
                 noise=(0.0, 0.25, 0.5, 1.0, 2.0, 4.0), room={"n_gaussians": 60_000},
                 depth_room={"n_gaussians": 60_000, **DEPTH_ROOM}),
    "quick": Plan(train_rooms=12, steps=300, ks=(5, 40), topk_ks=(5,), stratified_ks=(40,), noise=(0.0, 0.5),
                  room={"n_gaussians": 60_000}, timing_views=1, timing_size=(320, 240), timing_rounds=2,
                  rgb_views=2, rgb_size=(320, 240), stats_views=2, depth_room={"n_gaussians": 60_000, **DEPTH_ROOM}),
    "smoke": Plan(train_rooms=1, steps=2, ks=(5,), stratified_ks=(5,), noise=(0.0, 1.0),
                  room={"n_gaussians": 5000, "layers": 2.0, "n_objects": 3, "n_wall_objects": 1, "n_views": 4,
                        "width": 80, "height": 60, "dim": 32, "points_per_gaussian": 8},
                  seeds=2, views=2, rays=256, timing_views=1, timing_size=(64, 48), timing_rounds=1, rgb_ks=(10,),
                  rgb_views=1, rgb_size=(64, 48), stats_views=1, dense_gaussians=5000,
                  flat_room={"n_gaussians": 3000, "n_views": 1, "width": 64, "height": 48, "dim": 32},
                  depth_room={"n_gaussians": 5000, "n_objects": 3, "n_wall_objects": 1, "n_views": 4, "width": 80,
                              "height": 60, "dim": 32, "points_per_gaussian": 8, "layers": 4.0, "thickness": 0.05,
                              "opacity_beta": (1.0, 2.0)}),
}


@dataclass(frozen=True)
class TrainingRun:
    """One training run of the comparison: the feature renderer it trains through (sampler name
    and K, 0 for V-Render), the opacity-noise scale of the rooms it trains on, and the offset of
    its training seed (network initialisation and rays)."""

    sampler: str
    k: int = 0
    noise: float = 0.0
    seed: int = 0

    @property
    def label(self) -> str:
        """The renderer and noise (the same for every seed)."""
        name = LABELS[self.sampler] + (f" K={self.k}" if self.k else "")
        return name + (f", opacity noise {self.noise:g}" if self.noise else "")


def plan_runs(plan: Plan) -> list[TrainingRun]:
    """Every training run of ``plan``, each with seed offsets 0 .. ``plan.seeds`` - 1: V-Render,
    top-K at each of its K, Q-Render at each K, Stratified-K, and Q-Render K=40 at each noise
    scale (noise 0 is the clean Q-Render K=40 run, added if the K values lack 40)."""
    runs = [TrainingRun("volume")]
    runs += [TrainingRun("topk", k) for k in (plan.ks if plan.topk_ks is None else plan.topk_ks)]
    runs += [TrainingRun("quantile", k) for k in plan.ks]
    runs += [TrainingRun("stratified", k) for k in plan.stratified_ks]
    runs += [TrainingRun("quantile", NOISE_K, s) for s in plan.noise if s or NOISE_K not in plan.ks]
    return [TrainingRun(r.sampler, r.k, r.noise, seed) for seed in range(plan.seeds) for r in runs]
