"""``qr-cl view``: the server's routes and frames, a taken port, the overview and the scene's
cameras, and the page in a real headless Chromium (skipped where none is installed): its first
frame shows most of the scene's labelled classes, a key and a button step through the scene's
cameras, a query typed into its text box turns the view into that query's relevancy, and dragging
renders smaller frames, then the full one."""
from __future__ import annotations

import io
import json
import socket
import threading
import urllib.error
import urllib.parse
import urllib.request
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread, imsave

from qr_cl.app.cli import build_parser, main
from qr_cl.app.demo.command import ROOM_GAUSSIANS
from qr_cl.app.query.scene import load_query_scene
from qr_cl.app.query.text import QueryError
from qr_cl.app.scenes.room_config import SyntheticConfig
from qr_cl.app.scenes.synthetic import room_folder
from qr_cl.app.scenes.views import room_overview_cameras
from qr_cl.app.viewer.command import build_server
from qr_cl.app.viewer.frames import FrameRequest
from qr_cl.app.viewer.server import parse_frame_request
from qr_cl.app.viewer.views import scene_views
from qr_cl.scene import orbit_cameras
from tests.app.browser import Browser, find_chromium
from tests.app.query_helpers import tiny_checkpoint

SIZE = (320, 240)
#: A class shows in a frame when at least this share of the frame's pixels have its colour.
VISIBLE_SHARE = 0.003
#: Largest RGB distance (channels in [0,1]) of a pixel from its class's colour: JPEG and the
#: blending of edges move colours.
COLOUR_TOLERANCE = 0.1
#: The viewer's frame-time budget while moving, far below any 320x240 render, so that a drag always
#: asks for reduced frames however fast the machine is.
FRAME_MS = 0.01


@contextmanager
def serving(args: list[str]):
    """The viewer of ``qr-cl view`` ``args`` (on a free port), serving in a thread."""
    srv = build_server(build_parser().parse_args(["view", *args, "--port", "0"]))
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    try:
        yield srv
    finally:
        srv.shutdown()
        srv.server_close()
        thread.join()


@pytest.fixture(scope="module")
def server(tiny_room, tmp_path_factory):
    """The viewer of the tiny room with a small trained checkpoint, serving on a free port."""
    checkpoint = tiny_checkpoint(tiny_room, tmp_path_factory.mktemp("gsnet"))
    with serving([str(tiny_room), "--checkpoint", str(checkpoint), "--width", str(SIZE[0]), "--height",
                  str(SIZE[1]), "--frame-ms", str(FRAME_MS)]) as srv:
        yield srv


def _get(url: str) -> tuple[int, dict, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=60) as response:
            return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as err:
        return err.code, dict(err.headers), err.read()


def _frame_url(srv, **overrides) -> str:
    view = srv.view
    params = {"eye": ",".join(map(str, view["eye"])), "target": ",".join(map(str, view["target"])),
              "up": ",".join(map(str, view["up"])), "fov_y": view["fov_y"], "width": 96, "height": 72,
              "mode": "rgb", "query": "", "sampler": "quantile", "k": 20}
    params.update(overrides)
    return srv.url + "api/frame?" + urllib.parse.urlencode(params)


def test_frame_requests_are_checked():
    good = "eye=0,0,0&target=1,0,0&up=0,0,1&fov_y=60&width=64&height=48&mode=pca&sampler=topk&k=5"
    request = parse_frame_request(good)
    assert request.mode == "pca" and request.k == 5 and request.camera().width == 64
    for bad, message in (("eye=0,0&target=1,0,0&up=0,0,1&fov_y=60&width=64&height=48", "eye"),
                         (good.replace("mode=pca", "mode=depth"), "mode='depth'"),
                         (good.replace("width=64", "width=9999"), "9999x48"),
                         (good.replace("fov_y=60", "fov_y=x"), "fov_y='x'"),
                         (good.replace("sampler=topk", "sampler=fast"), "sampler='fast'")):
        with pytest.raises(QueryError, match=message):
            parse_frame_request(bad)


def _framed(view: dict, means: np.ndarray, size: tuple[int, int] = SIZE) -> float:
    """The share of ``means`` [N,3] in front of the page's camera ``view`` and inside its frame."""
    cam = FrameRequest(tuple(view["eye"]), tuple(view["target"]), tuple(view["up"]), view["fov_y"], *size).camera()
    xyz = means @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
    z = np.maximum(xyz[:, 2], 1e-9)
    u, v = cam.fx * xyz[:, 0] / z + cam.cx, cam.fy * xyz[:, 1] / z + cam.cy
    return float(np.mean((xyz[:, 2] > 0) & (u >= 0) & (u < size[0]) & (v >= 0) & (v < size[1])))


def test_the_overview_frames_the_scene(tiny_room):
    scene = load_query_scene(tiny_room)
    g, cams = scene.gaussians, scene.cameras
    views = scene_views(g, cams, *SIZE)
    assert [v["name"] for v in views] == ["overview", *(c.name for c in cams)]
    room = room_overview_cameras(g, *SIZE, n=1)[0]                       # the demo pictures' camera
    assert np.allclose(views[0]["eye"], room.position) and np.allclose(views[0]["up"], [0, 0, 1])
    assert _framed(views[0], g.means) > 0.9 and _framed(views[1], g.means) < 0.5
    assert np.allclose(views[1]["eye"], cams[0].position)
    turn = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])                # z up -> -y up, as COLMAP's scenes
    turned = replace(g, means=(g.means @ turn.T).astype(np.float32))
    moved = [replace(c, viewmat=c.viewmat @ np.block([[turn.T, np.zeros((3, 1))], [np.zeros((1, 3)), 1]]))
             for c in cams]
    orbit = scene_views(turned, moved, *SIZE)[0]
    assert np.dot(orbit["up"], [0, -1, 0]) > 0.9 and _framed(orbit, turned.means) > 0.95   # its cameras' up
    bare = scene_views(g, [], *SIZE, up_axis=2)
    assert len(bare) == 1 and bare[0]["up"] == [0, 0, 1] and _framed(bare[0], g.means) > 0.95
    assert np.allclose(bare[0]["eye"], orbit_cameras(g.means, 1, *SIZE)[0].position)   # qr-cl render --orbit's


def test_routes_and_frames(server):
    status, _, body = _get(server.url)
    assert status == 200 and b"<canvas" in body and b"viewer.js" in body
    status, headers, body = _get(server.url + "viewer.js")
    assert status == 200 and "javascript" in headers["Content-Type"] and b"api/frame" in body
    info = json.loads(_get(server.url + "api/scene")[2])
    assert info["modes"] == ["rgb", "pca", "classes", "relevancy"] and info["gaussians"] == 3000
    assert info["legend"] and all(e["colour"].startswith("#") for e in info["legend"])
    assert info["camera"]["width"] == SIZE[0] and info["camera"]["radius"] > 0
    assert info["camera"]["target_ms"] == FRAME_MS
    assert [v["name"] for v in info["camera"]["views"]][:2] == ["overview", "frame_000"]
    images = {}
    for mode, query in (("rgb", ""), ("pca", ""), ("classes", ""), ("relevancy", "wall"), ("relevancy", "floor")):
        status, headers, body = _get(_frame_url(server, mode=mode, query=query))
        assert status == 200 and headers["Content-Type"] == "image/jpeg" and float(headers["X-Render-Ms"]) > 0
        images[mode + query] = imread(io.BytesIO(body), format="jpeg").astype(np.float32) / 255
        assert images[mode + query].shape == (72, 96, 3) and images[mode + query].std() > 0.02, mode
    keys = list(images)
    assert all(np.abs(images[a] - images[b]).mean() > 0.02 for i, a in enumerate(keys) for b in keys[i + 1:])
    status, _, body = _get(_frame_url(server, mode="relevancy", query="chiar"))
    assert status == 404 and "closest: chair" in json.loads(body)["error"]
    status, _, body = _get(_frame_url(server, width=5))
    assert status == 400 and "5x72" in json.loads(body)["error"]


def test_a_taken_port_is_one_line(tiny_room, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["view", str(tiny_room), "--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"qr-cl: error: port {port} on 127.0.0.1 is in use") and err.count("\n") == 1
    assert main(["view", str(tiny_room), "--frame-ms", "0"]) == 2
    assert capsys.readouterr().err == "qr-cl: error: --frame-ms must be positive, got 0.0\n"


@pytest.fixture(scope="module")
def browser():
    executable = find_chromium()
    if executable is None:
        pytest.skip("no chromium installed (Debian: apt-get install chromium)")
    b = Browser(executable)
    yield b
    b.close()


@contextmanager
def labelled_viewer(room: Path, tmp: Path):
    """(the viewer of ``room`` with its ground truth as features, the names of its labelled
    classes): each Gaussian carries its label's text feature, so that classes mode paints every
    Gaussian its labelled class."""
    scene = load_query_scene(room)
    labels, table = scene.data.gaussian_labels, scene.classes
    rows = np.minimum(np.searchsorted(table.ids, labels), len(table.ids) - 1)
    labelled = labels >= 0
    assert (table.ids[rows[labelled]] == labels[labelled]).all()
    np.save(tmp / "labels.npy", np.where(labelled[:, None], table.text_features[rows], 0).astype(np.float32))
    with serving([str(room), "--features", str(tmp / "labels.npy"), "--width", str(SIZE[0]),
                  "--height", str(SIZE[1])]) as srv:
        yield srv, {table.names[r] for r in np.unique(rows[labelled])}


def visible_classes(image: np.ndarray, legend: list[dict], share: float = VISIBLE_SHARE) -> dict[str, float]:
    """{class name: share of the pixels of ``image`` [H,W,3] in [0,1]} for the classes of
    ``legend`` (the viewer's, name and #rrggbb colour) that paint at least ``share`` of its
    pixels, a pixel counting for the legend colour nearest to it within :data:`COLOUR_TOLERANCE`."""
    colours = np.array([[int(e["colour"][i:i + 2], 16) / 255 for i in (1, 3, 5)] for e in legend])
    distance = np.linalg.norm(image[:, :, None, :] - colours[None, None], axis=-1)
    nearest = np.where(distance.min(-1) < COLOUR_TOLERANCE, distance.argmin(-1), -1)
    counts = np.bincount(nearest[nearest >= 0], minlength=len(legend)) / nearest.size
    return {e["name"]: float(c) for e, c in zip(legend, counts) if c >= share}


def _view_frame(browser, view: str) -> np.ndarray:
    """The page's screenshot once it has drawn the full frame of the view named ``view``."""
    browser.wait_for(f"document.body.dataset.full === '1' && document.body.dataset.view === {view!r}")
    return browser.screenshot("view")


def first_view_classes(srv, labelled: set[str], browser, out: Path) -> tuple[dict, dict]:
    """(classes the page's first frame shows in classes mode, classes the scene's first camera
    shows), each {name: share of the pixels} (:func:`visible_classes`) among ``labelled``; the
    frames go to ``out``. Steps there with C, back with shift+C, round to the last camera with the
    page's previous-view button."""
    legend = [e for e in srv.scene_info()["legend"] if e["name"] in labelled]
    views = srv.view["views"]
    browser.page("Page.navigate", {"url": srv.url + "?mode=classes"})
    first = _view_frame(browser, "overview")
    browser.press("c")                                                    # the scene's first camera
    camera = _view_frame(browser, views[1]["name"])
    assert browser.evaluate("document.getElementById('view-name').textContent").startswith(views[1]["name"])
    imsave(out / "overview.png", first)
    imsave(out / "first_camera.png", camera)
    browser.press("c", shift=True)                                        # back to the overview
    assert np.abs(_view_frame(browser, "overview") - first).mean() < 0.01
    browser.click("prev-view")                                            # round to the last camera
    last = _view_frame(browser, views[-1]["name"])
    assert np.abs(last - camera).mean() > 0.02 and np.abs(last - first).mean() > 0.02
    return visible_classes(first, legend), visible_classes(camera, legend)


def _check_first_view(room: Path, browser, tmp: Path) -> None:
    with labelled_viewer(room, tmp) as (srv, labelled):
        shown, old = first_view_classes(srv, labelled, browser, tmp)
    (tmp / "first_view.json").write_text(json.dumps({"labelled": sorted(labelled), "first view": shown,
                                                     "first camera": old}, indent=1))
    assert len(shown) > len(labelled) / 2, f"the first view shows {sorted(shown)} of {sorted(labelled)} ({tmp})"
    # what the page opened on before: the scene's first camera fails the same check
    assert len(old) <= len(labelled) / 2, f"the first camera shows {sorted(old)} of {sorted(labelled)} ({tmp})"


def test_the_first_view_shows_the_scene(tiny_room, browser, tmp_path):
    _check_first_view(tiny_room, browser, tmp_path)


@pytest.mark.slow
def test_the_first_view_shows_the_demo_room(browser, tmp_path):
    """The same on the held-out room of ``qr-cl demo`` (its default seed 0 + 1000, 60k Gaussians;
    generated into the scene cache on first use)."""
    room = room_folder(SyntheticConfig(seed=1000, n_gaussians=ROOM_GAUSSIANS["3dgs"], style="3dgs", features="clip"))
    _check_first_view(room, browser, tmp_path)


def test_a_typed_query_changes_the_page(server, browser, tmp_path):
    browser.page("Page.navigate", {"url": server.url})
    browser.wait_for("document.body.dataset.full === '1' && document.body.dataset.mode === 'rgb'")
    rgb = browser.screenshot("view")
    assert rgb.shape == (SIZE[1], SIZE[0], 3) and rgb.std() > 0.02
    shots = {}
    for text in ("wall", "floor"):
        frames = int(browser.evaluate("document.body.dataset.frames"))
        browser.evaluate("document.getElementById('query').select()")        # typing replaces the box's text
        browser.evaluate("document.getElementById('query').focus()")
        browser.type_text(text)
        browser.wait_for(f"+document.body.dataset.frames > {frames} && document.body.dataset.mode === 'relevancy'"
                         " && document.body.dataset.full === '1'")
        assert browser.evaluate("document.getElementById('query').value") == text
        assert browser.evaluate("document.body.dataset.error") == ""
        shots[text] = browser.screenshot("view")
    imsave(tmp_path / "wall.png", shots["wall"])
    assert np.abs(shots["wall"] - rgb).mean() > 0.05, f"the relevancy view looks like the RGB one ({tmp_path})"
    assert np.abs(shots["wall"] - shots["floor"]).mean() > 0.02, "two queries gave the same picture"
    box = browser.evaluate("(() => { const r = document.getElementById('view').getBoundingClientRect();"
                           " return [r.x + r.width / 2, r.y + r.height / 2]; })()")
    browser.drag(box[0], box[1], box[0] + 120, box[1] + 20,
                 until="+document.body.dataset.reduced > 0")                 # smaller frames while moving
    browser.wait_for("document.body.dataset.full === '1'", timeout=30)       # then the full one
    assert np.abs(browser.screenshot("view") - shots["floor"]).mean() > 0.02, "the drag did not move the camera"
    assert "render" in browser.evaluate("document.getElementById('time').textContent")
