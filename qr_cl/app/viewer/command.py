"""``qr-cl view``: a web viewer of a scene on localhost, every frame rendered by qr-cl on the CPU.

The page (``static/index.html``) opens on an overview that frames the whole scene (a room seen
from above as in the pictures of ``qr-cl demo``, an orbit view otherwise; :mod:`.views`); C and
shift+C, or its view buttons, step through the scene's own cameras and back to the overview. It
orbits (drag), pans (right- or shift-drag), zooms (wheel) and flies (W/A/S/D, Q/E) the camera;
shows RGB, feature PCA, predicted classes (with a legend) or the relevancy of a query typed into
its text box; K and the sampler are selectable. While the camera moves it asks for smaller
frames, sized from the last frame's render time to keep about ``--frame-ms`` (default
:data:`TARGET_MS`) a frame, and the full frame once the camera rests; it shows the frame time.
"""
from __future__ import annotations

import argparse
import errno
import sys

from ...runtime import DEFAULTS, SAMPLERS
from ..arguments import AXES, nonnegative_int, port_number, positive_int
from ..process import cap_kernel_threads
from ..query.relevancy import METHODS
from ..query.scene import load_query_scene, scene_features
from ..query.text import QueryError, TextEncoder, TextLookup, open_clip_encoder
from .frames import FrameRenderer, FrameRequest
from .server import ViewerServer, initial_view

#: Render time per frame (ms) the page aims at while the camera moves (viewer.js reads it from /api/scene).
TARGET_MS = 60
#: Size (W, H) of the frames rendered once before serving, to build the kernels.
WARM_UP_SIZE = (64, 48)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl view``."""
    parser.add_argument("scene", help="scene folder (point_cloud.ply, cameras.json, classes.json) "
                                      "or a .ply/.splat")
    src = parser.add_mutually_exclusive_group()
    src.add_argument("--checkpoint", help="GS-Net checkpoint.pt: adds the PCA, classes and relevancy modes")
    src.add_argument("--features", help="per-Gaussian features (.npy [N,C] or a PLY with feature_<i> properties)")
    parser.add_argument("--port", type=port_number, default=8000, help="port on --host (default 8000; 0 = any free one)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to serve on (default 127.0.0.1, this machine only)")
    parser.add_argument("--width", type=positive_int, default=DEFAULTS.width,
                        help=f"full frame width, px (default {DEFAULTS.width})")
    parser.add_argument("--height", type=positive_int, default=480, help="full frame height, px (default 480)")
    parser.add_argument("--frame-ms", type=float, default=TARGET_MS,
                        help=f"render time per frame (ms) to keep while the camera moves; frames shrink "
                             f"to fit it (default {TARGET_MS})")
    parser.add_argument("--up-axis", type=int, choices=AXES, default=2,
                        help="world up axis for a scene without cameras (2 = z, 1 = y)")
    parser.add_argument("--sampler", choices=SAMPLERS, default=DEFAULTS.sampler, help="initial sampler of the feature modes")
    parser.add_argument("-k", type=positive_int, default=DEFAULTS.k, help=f"initial K (default {DEFAULTS.k})")
    parser.add_argument("--score", choices=METHODS, default="relevancy", help="relevancy (default) or cosine")
    parser.add_argument("--clip-weights", help="local OpenCLIP weights file for arbitrary query text (qr-cl[clip])")
    parser.add_argument("--clip-model", default="ViT-B-32", help="OpenCLIP architecture (default ViT-B-32)")
    parser.add_argument("--level", type=nonnegative_int, default=0, help="LangSplat mask level of a scene folder (default 0)")


def build_server(args: argparse.Namespace, encoder: TextEncoder | None = None) -> ViewerServer:
    """The viewer's server for ``args`` (bound, not yet serving); ``encoder`` replaces the one
    ``--clip-weights`` loads. OSError when the port is taken."""
    if not args.frame_ms > 0:
        raise QueryError(f"--frame-ms must be positive, got {args.frame_ms}")
    cap_kernel_threads()
    scene = load_query_scene(args.scene, args.level)
    if encoder is None and args.clip_weights:
        encoder = open_clip_encoder(args.clip_weights, args.clip_model)
    features = scene_features(scene, args.checkpoint, args.features)
    lookup = TextLookup(features.shape[1], scene.classes, encoder) if features is not None else None
    renderer = FrameRenderer(scene, features, lookup, args.score)
    view = dict(initial_view(renderer, args.width, args.height, args.up_axis), target_ms=args.frame_ms)
    server = ViewerServer((args.host, args.port), renderer, view, args.k, args.sampler)
    try:
        renderer.warm_up(FrameRequest(tuple(view["eye"]), tuple(view["target"]), tuple(view["up"]), view["fov_y"],
                                      WARM_UP_SIZE[0], WARM_UP_SIZE[1], sampler=args.sampler, k=args.k))
    except BaseException:
        server.server_close()
        raise
    return server


def run(args: argparse.Namespace) -> int:
    """Serve the viewer until interrupted (Ctrl-C). A taken port or bad input: one line, exit 2."""
    try:
        server = build_server(args)
    except QueryError as exc:
        print(f"qr-cl: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.errno != errno.EADDRINUSE:
            raise
        print(f"qr-cl: error: port {args.port} on {args.host} is in use (choose another with --port, "
              "or --port 0 for any free one)", file=sys.stderr)
        return 2
    print(f"qr-cl view: {server.renderer.scene.name} ({len(server.renderer.scene.gaussians)} Gaussians, "
          f"modes {', '.join(server.renderer.modes())}) at {server.url}  (Ctrl-C stops)", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    return 0
