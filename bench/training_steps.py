"""Training step time and busy cores of ``qr-cl train``, for this checkout or another install and this one.

A step's cost is measured as the difference of a long and a short run (``--long`` and
``--short`` steps), so start-up (imports, scene loading, kernel builds, the first whole-view
selections) cancels: ms per step = (wall_long - wall_short) / (long - short), and the cores a
step keeps busy = (cpu_long - cpu_short) / (wall_long - wall_short), CPU being the user and
system time of the child process (all its threads: torch, the convolution helper, PoCL's
workers). The installs run alternately, one pair of runs each per round, so that a machine whose
speed drifts affects them alike::

    python bench/training_steps.py ~/.cache/qr-cl/scenes/splat-room-0-* --base PYTHON_OR_CHECKOUT --rounds 3

(``--base``: see bench/ab.py.)

Options this script does not know are passed to ``qr-cl train`` (e.g. ``--net tiny``). Prints a
Markdown table (the median over rounds of each install, and each one's speed relative
to the first, the base when there is one: the ratio of the medians, and the median of the rounds' ratios, which
a drift between rounds moves less) and writes it to ``--out`` when given. A previous release
that fails now and then (3d3ed6a's intermittent KeyError when two threads built one program)
can be measured with ``--retries``: a round of an install whose run fails is run again, and the
table counts the failed runs.
"""
from __future__ import annotations

import os
import resource
import statistics
import tempfile
import time
from pathlib import Path

from ab import Install, add_base_option, installs
from benchutil import arguments, print_table, room_parser


class RunFailed(RuntimeError):
    """A ``qr-cl train`` run that exited with an error (its message holds the command and stderr's tail)."""


def run_train(install: Install, room: str, steps: int, extra: list[str]) -> tuple[float, float]:
    """(wall s, CPU s of the child) of ``qr-cl train room --steps steps`` in ``install``; raises
    :class:`RunFailed` if it fails."""
    with tempfile.TemporaryDirectory() as out:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        proc = install.run(["-m", "qr_cl.app.cli", "train", room, "--out", out, "--steps", str(steps),
                            "--checkpoint-every", "100000", *extra], capture_output=True, text=True, cwd=out)
        if proc.returncode:
            raise RunFailed(f"{install.label}: qr-cl train {room} --steps {steps} failed "
                            f"(rc {proc.returncode}):\n{proc.stderr[-4000:]}")
        wall = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def measure(runs_of: list[Install], args,
            extra: list[str]) -> tuple[dict[str, list[tuple[float, float]]], dict[str, int]]:
    """({label: [(ms per step, cores busy) per round]}, {label: failed runs}) of the installs
    ``runs_of``, alternately, ``args.rounds`` rounds of a short and a long run each."""
    results: dict[str, list[tuple[float, float]]] = {install.label: [] for install in runs_of}
    failed = dict.fromkeys(results, 0)
    for r in range(args.rounds):
        for install in runs_of:
            label = install.label
            while True:
                try:
                    short = run_train(install, args.room, args.short, extra)
                    long = run_train(install, args.room, args.long, extra)
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
    return results, failed


def main() -> None:
    parser = room_parser(__doc__)
    add_base_option(parser, required=False)
    parser.add_argument("--short", type=arguments.positive_int, default=30, help="steps of the short run (default 30)")
    parser.add_argument("--long", type=arguments.positive_int, default=120, help="steps of the long run (default 120)")
    parser.add_argument("--rounds", type=arguments.positive_int, default=3, help="rounds (default 3)")
    parser.add_argument("--retries", type=arguments.nonnegative_int, default=0,
                        help="failed runs of an install to tolerate over the whole measurement, each one's round "
                             "run again (default 0: stop at the first failure); the table counts them")
    args, extra = parser.parse_known_args()            # the rest are qr-cl train options
    if args.long <= args.short:
        parser.error(f"--long ({args.long}) must exceed --short ({args.short})")
    with installs(args.base) as runs_of:
        results, failed = measure(runs_of, args, extra)
    first_label = next(iter(results))
    first = [ms for ms, _ in results[first_label]]
    lines = [f"`qr-cl train {Path(args.room).name}` {' '.join(extra)}: steps {args.short} and {args.long}, "
             f"{args.rounds} rounds, {os.cpu_count()} CPUs", "",
             f"| install | ms per step (median) | rounds | cores busy (median) | steps/s vs {first_label} "
             f"| the same, median of the rounds' ratios | failed runs |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for label in results:
        ms = [m for m, _ in results[label]]
        cores = statistics.median(c for _, c in results[label])
        lines.append(f"| {label} | {statistics.median(ms):.1f} | {', '.join(f'{m:.1f}' for m in ms)} | {cores:.2f} | "
                     f"{statistics.median(first) / statistics.median(ms):.2f}x | "
                     f"{statistics.median(f / m for f, m in zip(first, ms)):.2f}x | {failed[label]} |")
    print_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
