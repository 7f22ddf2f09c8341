"""``qr-cl view``: the server's routes and frames, a taken port, and the page in a real headless
Chromium (skipped where none is installed): it draws a frame, a query typed into its text box
turns the view into that query's relevancy, and dragging renders smaller frames, then the full one."""
from __future__ import annotations

import io
import json
import socket
import threading
import urllib.error
import urllib.parse
import urllib.request

import numpy as np
import pytest
from matplotlib.image import imread, imsave

from qr_cl.app.cli import build_parser, main
from qr_cl.app.query.text import QueryError
from qr_cl.app.viewer.command import build_server
from qr_cl.app.viewer.server import parse_frame_request
from tests.app.browser import Browser, find_chromium
from tests.app.query_helpers import tiny_checkpoint

SIZE = (320, 240)
#: The viewer's frame-time budget while moving, far below any 320x240 render, so that a drag always
#: asks for reduced frames however fast the machine is.
FRAME_MS = 0.01


@pytest.fixture(scope="module")
def server(tiny_room, tmp_path_factory):
    """The viewer of the tiny room with a small trained checkpoint, serving on a free port."""
    checkpoint = tiny_checkpoint(tiny_room, tmp_path_factory.mktemp("gsnet"))
    args = build_parser().parse_args(["view", str(tiny_room), "--checkpoint", str(checkpoint), "--port", "0",
                                      "--width", str(SIZE[0]), "--height", str(SIZE[1]),
                                      "--frame-ms", str(FRAME_MS)])
    srv = build_server(args)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()
    thread.join()


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
