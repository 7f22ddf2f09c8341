"""Helpers shared by the benchmarks (imported by name: bench/ is on sys.path under pytest)."""
from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path


def run(benchmark, fn, full: bool, rounds: int = 5):
    """Time ``fn`` (which must finish its OpenCL queue) with warm-up in full mode, once in smoke."""
    return benchmark.pedantic(fn, rounds=rounds if full else 1, iterations=1,
                              warmup_rounds=1 if full else 0)


def checkout_module(name: str):
    """qr_cl/app/<name>.py of this checkout, loaded from its file (it must need the standard
    library only): a script's worker that runs under another install of qr-cl (see ab.py) uses
    this checkout's timing and argument checks, not that install's."""
    spec = importlib.util.spec_from_file_location(
        f"qr_cl_checkout_{name}", Path(__file__).resolve().parents[1] / "qr_cl" / "app" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


timing = checkout_module("timing")
arguments = checkout_module("arguments")


def room_parser(doc: str) -> argparse.ArgumentParser:
    """The options every script measuring one demo room takes: its description (the first paragraph
    of ``doc``, the script's docstring), the positional ``room`` and ``--out``."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("room", help="a scene folder (e.g. a demo room in ~/.cache/qr-cl/scenes)")
    parser.add_argument("--out", type=Path, help="write the table to this Markdown file")
    return parser


def fox_and_dense_room(data: Path | None, width: int, height: int, dense_n: int) -> dict:
    """{name: (Gaussians, Camera)} of this checkout's qr_cl: the real fox (where ``data`` holds
    it; its second orbit camera) and the procedural dense room of ``dense_n`` Gaussians, both
    width x height."""
    import warnings

    import qr_cl
    from qr_cl.app.scenes.procedural import dense_room
    scenes = {}
    fox = None if data is None else data / "wakufactory-fox" / "fox.ply"
    if fox is not None and fox.is_file():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            g = qr_cl.load_ply(fox)
        scenes["fox"] = (g, qr_cl.orbit_cameras(g.means, 8, width, height)[1])
    scenes[f"dense-room-{dense_n // 1000}k"] = dense_room(dense_n, width=width, height=height)
    return scenes


def print_table(table: str, out: Path | None) -> None:
    """Print a Markdown table and, when ``out`` is given, write it there (folders made)."""
    print(table)
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(table + "\n")
