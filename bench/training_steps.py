"""Training step time and busy cores of ``qr-cl train``, for one install or several back to back.

A step's cost is measured as the difference of a long and a short run (``--long`` and
``--short`` steps), so start-up (imports, scene loading, kernel builds, the first whole-view
selections) cancels: ms per step = (wall_long - wall_short) / (long - short), and the cores a
step keeps busy = (cpu_long - cpu_short) / (wall_long - wall_short), CPU being the user and
system time of the child process (all its threads: torch, the convolution helper, PoCL's
workers). The installs run alternately, one pair of runs each per round, so that a machine whose
speed drifts affects them alike::

    python bench/training_steps.py ~/.cache/qr-cl/scenes/splat-room-0-* \\
        --python this=python --python before=<venv of the previous release>/bin/python --rounds 3

Options this script does not know are passed to ``qr-cl train`` (e.g. ``--net tiny``). Prints a
Markdown table (the median over rounds of each install, and each one's speed relative
to the first ``--python``: the ratio of the medians, and the median of the rounds' ratios, which
a drift between rounds moves less) and writes it to ``--out`` when given. A previous release
that fails now and then (3d3ed6a's intermittent KeyError when two threads built one program)
can be measured with ``--retries``: a round of an install whose run fails is run again, and the
table counts the failed runs.
"""
from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchutil import print_table, room_parser


class RunFailed(RuntimeError):
    """A ``qr-cl train`` run that exited with an error (its message holds the command and stderr's tail)."""


def run_train(python: str, room: str, steps: int, extra: list[str]) -> tuple[float, float]:
    """(wall s, CPU s of the child) of ``qr-cl train room --steps steps`` under ``python`` (the
    install that interpreter imports); raises :class:`RunFailed` if it fails."""
    with tempfile.TemporaryDirectory() as out:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        proc = subprocess.run([python, "-m", "qr_cl.app.cli", "train", room, "--out", out, "--steps", str(steps),
                               "--checkpoint-every", "100000", *extra], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True, cwd=out)   # not the checkout: -m imports the cwd
        if proc.returncode:
            raise RunFailed(f"{python} -m qr_cl.app.cli train {room} --steps {steps} failed "
                            f"(rc {proc.returncode}):\n{proc.stderr[-4000:]}")
        wall = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = room_parser(__doc__)
    parser.add_argument("--python", action="append", metavar="LABEL=PYTHON",
                        help="an install to measure (repeatable; default this=<this interpreter>)")
    parser.add_argument("--short", type=int, default=30, help="steps of the short run (default 30)")
    parser.add_argument("--long", type=int, default=120, help="steps of the long run (default 120)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds (default 3)")
    parser.add_argument("--retries", type=int, default=0,
                        help="failed runs of an install to tolerate over the whole measurement, each one's round "
                             "run again (default 0: stop at the first failure); the table counts them")
    args, extra = parser.parse_known_args()            # the rest are qr-cl train options
    if args.long <= args.short:
        parser.error(f"--long ({args.long}) must exceed --short ({args.short})")
    installs = [p.split("=", 1) for p in (args.python or [f"this={sys.executable}"])]
    if any(len(p) != 2 for p in installs):
        parser.error("--python takes LABEL=PYTHON")
    results: dict[str, list[tuple[float, float]]] = {label: [] for label, _ in installs}
    failed = dict.fromkeys(results, 0)
    for r in range(args.rounds):
        for label, python in installs:
            while True:
                try:
                    short = run_train(python, args.room, args.short, extra)
                    long = run_train(python, args.room, args.long, extra)
                    break
                except RunFailed as error:
                    failed[label] += 1
                    if failed[label] > args.retries:
                        raise SystemExit(str(error)) from None
                    print(f"round {r + 1} {label}: failed ({str(error).splitlines()[-1]}); again", flush=True)
            wall, cpu = long[0] - short[0], long[1] - short[1]
            results[label].append((1000 * wall / (args.long - args.short), cpu / wall))
            print(f"round {r + 1} {label}: {results[label][-1][0]:.1f} ms/step, {results[label][-1][1]:.2f} cores",
                  flush=True)
    first = [ms for ms, _ in results[installs[0][0]]]
    lines = [f"`qr-cl train {Path(args.room).name}` {' '.join(extra)}: steps {args.short} and {args.long}, "
             f"{args.rounds} rounds, {os.cpu_count()} CPUs", "",
             f"| install | ms per step (median) | rounds | cores busy (median) | steps/s vs {installs[0][0]} "
             f"| the same, median of the rounds' ratios | failed runs |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for label, _ in installs:
        ms = [m for m, _ in results[label]]
        cores = statistics.median(c for _, c in results[label])
        lines.append(f"| {label} | {statistics.median(ms):.1f} | {', '.join(f'{m:.1f}' for m in ms)} | {cores:.2f} | "
                     f"{statistics.median(first) / statistics.median(ms):.2f}x | "
                     f"{statistics.median(f / m for f, m in zip(first, ms)):.2f}x | {failed[label]} |")
    print_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
