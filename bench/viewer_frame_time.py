"""The web viewer's frame time on the real fox (50k Gaussians, SH degree 0) at 640x480 (RGB mode).

Three figures, each the minimum and median over ``--rounds`` frames after a warm-up:

* ``render``: :meth:`qr_cl.app.viewer.frames.FrameRenderer.render` (camera from the request, the
  fused V-Render of the SH colours, 8-bit image): the time the page shows as "render";
* ``render + JPEG``: what the server spends per frame;
* ``HTTP frame``: a whole ``GET /api/frame`` to a viewer on localhost (render, JPEG, transfer),
  the camera orbiting a little every frame as when the user drags::

    python bench/viewer_frame_time.py --data ../shared/data --rounds 20
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import urllib.parse
import urllib.request
import warnings
from pathlib import Path

import numpy as np

from qr_cl.app.process import cap_kernel_threads
from qr_cl.app.query.scene import load_query_scene
from qr_cl.app.timing import measure
from qr_cl.app.viewer.frames import FrameRenderer, FrameRequest
from qr_cl.app.viewer.server import ViewerServer, encode_jpeg, initial_view

DATA = Path(os.environ.get("QR_CL_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def orbiting(view: dict, width: int, height: int):
    """A function returning the next FrameRequest of a camera orbiting ``view``'s target by 2
    degrees a frame."""
    eye, target = np.asarray(view["eye"]), np.asarray(view["target"])
    step = [0]

    def next_request() -> FrameRequest:
        step[0] += 1
        a = math.radians(2 * step[0])
        rot = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        return FrameRequest(tuple(target + rot @ (eye - target)), tuple(target), tuple(view["up"]),
                            view["fov_y"], width, height)
    return next_request


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", default=str(DATA), help="folder of the real scenes (default ../shared/data)")
    parser.add_argument("--rounds", type=int, default=20, help="frames timed per figure (default 20)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    args = parser.parse_args(argv)
    fox = Path(args.data) / "wakufactory-fox" / "fox.ply"
    if not fox.is_file():
        print(f"error: {fox}: no such file (--data)", file=sys.stderr)
        return 2
    cap_kernel_threads()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        renderer = FrameRenderer(load_query_scene(fox))
    view = initial_view(renderer, args.width, args.height, up_axis=2)
    requests = orbiting(view, args.width, args.height)
    server = ViewerServer(("127.0.0.1", 0), renderer, view)
    threading.Thread(target=server.serve_forever, daemon=True).start()

    def http_frame() -> None:
        r = requests()
        query = urllib.parse.urlencode({"eye": ",".join(map(str, r.eye)), "target": ",".join(map(str, r.target)),
                                        "up": ",".join(map(str, r.up)), "fov_y": r.fov_y, "width": r.width,
                                        "height": r.height, "mode": "rgb"})
        with urllib.request.urlopen(server.url + "api/frame?" + query) as response:
            response.read()

    figures = {"render": lambda: renderer.render(requests()),
               "render + JPEG": lambda: encode_jpeg(renderer.render(requests())[0]),
               "HTTP frame": http_frame}
    print(f"fox ({len(renderer.scene.gaussians)} Gaussians), {args.width}x{args.height}, RGB, "
          f"{os.environ['POCL_MAX_PTHREAD_COUNT']} PoCL threads, {args.rounds} frames each")
    for name, call in figures.items():
        t = measure(call, args.rounds, warmup=2)
        print(f"{name:>14}: min {1000 * t['min_s']:6.1f} ms, median {1000 * t['median_s']:6.1f} ms")
    server.shutdown()
    server.server_close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
