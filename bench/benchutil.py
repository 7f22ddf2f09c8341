"""Helpers shared by the benchmarks (imported by name: bench/ is on sys.path under pytest)."""
from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from typing import Callable


def run(benchmark, fn, full: bool, rounds: int = 5):
    """Time ``fn`` (which must finish its OpenCL queue) with warm-up in full mode, once in smoke."""
    return benchmark.pedantic(fn, rounds=rounds if full else 1, iterations=1,
                              warmup_rounds=1 if full else 0)


def _checkout_timing():
    """qr_cl/app/timing.py of this checkout, loaded from its file (it needs the standard library
    only): scripts that measure another install of qr-cl time both with the same helper."""
    spec = importlib.util.spec_from_file_location(
        "qr_cl_checkout_timing", Path(__file__).resolve().parents[1] / "qr_cl" / "app" / "timing.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


timing = _checkout_timing()


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


def ab_arguments(description: str, rounds: int, calls: int) -> argparse.ArgumentParser:
    """The options of a script timing this checkout against another install: ``--base PYTHON``,
    ``--rounds``, ``--calls``, and the hidden ``--worker FILE`` under which it measures the
    install it runs in (see :func:`ab_rounds`)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--base", metavar="PYTHON", help="the interpreter of the other install")
    ap.add_argument("--rounds", type=int, default=rounds, help="runs of each install, alternating")
    ap.add_argument("--calls", type=int, default=calls, help="timed calls per run, after a warm-up")
    ap.add_argument("--worker", type=Path, help=argparse.SUPPRESS)   # inputs file: measure, print JSON
    return ap


def ab_parse(ap: argparse.ArgumentParser, measure: Callable[[Path, int], dict]) -> argparse.Namespace | None:
    """The parsed options of an :func:`ab_arguments` parser; under ``--worker`` it prints the JSON
    of ``measure(worker file, calls)`` (the install this process imports) and returns None."""
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(measure(args.worker, args.calls)))
        return None
    if not args.base:
        ap.error("--base PYTHON is required")
    return args


def ab_rounds(script: str, base: str, inputs: Path, rounds: int, calls: int,
              describe: Callable[[dict], str]) -> dict[str, list[dict]]:
    """{"base": [...], "this": [...]}: the JSON that ``script --worker inputs --calls calls``
    prints last, run ``rounds`` times under ``base`` and this interpreter alternately, each in a
    fresh process in ``inputs``' folder (not the checkout: ``python script`` imports its install,
    not this tree). Prints each run as ``describe`` words it; exits with the tail of a failed
    run's stderr."""
    runs: dict[str, list[dict]] = {"base": [], "this": []}
    for r in range(rounds):
        for label, python in (("base", base), ("this", sys.executable)):
            cmd = [python, script, "--worker", str(inputs), "--calls", str(calls)]
            proc = subprocess.run(cmd, capture_output=True, text=True, cwd=inputs.parent)
            if proc.returncode:
                sys.exit(f"{label} run failed ({' '.join(cmd)}):\n{proc.stderr[-3000:]}")
            runs[label].append(json.loads(proc.stdout.strip().splitlines()[-1]))
            print(f"round {r + 1} {label}: {describe(runs[label][-1])}", flush=True)
    return runs


def print_table(table: str, out: Path | None) -> None:
    """Print a Markdown table and, when ``out`` is given, write it there (folders made)."""
    print(table)
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(table + "\n")
