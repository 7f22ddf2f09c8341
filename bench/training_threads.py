"""Where the wall time of a GS-Net training step goes, thread by thread, in one process set up as
``qr-cl train`` sets itself up.

After ``--warmup`` steps, ``--steps`` steps of :meth:`~qr_cl.app.training.trainer.Trainer.train_step`
are run and two things are read:

* the share of the steps' wall time each thread of the process was on a CPU (``/proc/self/task``):
  the training thread, the convolution helper, the thread making the next step's rays, and the
  rest (PoCL's workers); their sum is the cores a step keeps busy;
* on the training thread, its wall time in convolutions split over the threads (its own block, and
  the wait for the helper's after it), in convolutions that run whole, and in everything else
  (batch norm, ReLU, de-voxelization, head, blend, loss, their backward, Adam, Python), the
  convolutions timed by wrapping :func:`qr_cl.backbone.conv.run_tasks`.

The second part says what would have to run on both cores for a step to keep two busy::

    python bench/training_threads.py ~/.cache/qr-cl/scenes/splat-room-0-* --out REPORT.md
"""
from __future__ import annotations

import os
import tempfile
import threading
import time
from pathlib import Path

from benchutil import print_table, room_parser
from qr_cl.app.process import cap_kernel_threads, keep_freed_memory, torch_threads
from qr_cl.app.training.config import TrainConfig
from qr_cl.app.training.trainer import Trainer, conv_thread_count
from qr_cl.backbone import conv


def thread_cpu() -> dict[int, float]:
    """CPU seconds (user + system) of each thread of this process, by thread id."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for task in Path("/proc/self/task").iterdir():
        try:
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except FileNotFoundError:                 # a thread that ended meanwhile
            continue
        out[int(task.name)] = (int(fields[11]) + int(fields[12])) / tick
    return out


class ConvClock:
    """Wraps :func:`conv.run_tasks` to time, on the calling thread, split convolutions (its own
    block, then the wait for the others) and those that run whole."""

    def __init__(self) -> None:
        self.own = self.wait = self.whole = 0.0
        self.inner = conv.run_tasks

    def __call__(self, tasks: list) -> None:
        start = time.perf_counter()
        if conv._helpers is None or len(tasks) == 1:
            self.inner(tasks)
            self.whole += time.perf_counter() - start
            return
        done = []
        first = tasks[0]

        def timed_first() -> None:
            first()
            done.append(time.perf_counter())
        self.inner([timed_first, *tasks[1:]])
        end = time.perf_counter()
        self.own += done[0] - start
        self.wait += end - done[0]


def main() -> None:
    parser = room_parser(__doc__)
    parser.add_argument("--steps", type=int, default=30, help="steps measured (default 30)")
    parser.add_argument("--warmup", type=int, default=8, help="steps run first, not measured (default 8)")
    args = parser.parse_args()
    cap_kernel_threads()
    keep_freed_memory()
    clock = ConvClock()
    conv.run_tasks = clock
    with tempfile.TemporaryDirectory() as out, torch_threads(1):
        trainer = Trainer(TrainConfig(scenes=[args.room], out=out, steps=args.warmup + args.steps + 1))
        try:
            with conv.conv_threads(conv_thread_count()):
                for _ in range(args.warmup):
                    trainer.train_step()
                clock.own = clock.wait = clock.whole = 0.0
                names = {t.native_id: t.name for t in threading.enumerate()}
                before, start = thread_cpu(), time.perf_counter()
                for _ in range(args.steps):
                    trainer.train_step()
                wall, after = time.perf_counter() - start, thread_cpu()
                names.update({t.native_id: t.name for t in threading.enumerate()})
        finally:
            trainer.close()
    busy: dict[str, float] = {}
    for tid, cpu in after.items():
        name = names.get(tid, "other (PoCL's workers)")
        name = "training thread" if name == "MainThread" else name.rstrip("_0123456789")
        busy[name] = busy.get(name, 0.0) + (cpu - before.get(tid, 0.0)) / wall
    ms = 1000 / args.steps
    rest = wall - clock.own - clock.wait - clock.whole
    lines = [f"`python bench/training_threads.py {Path(args.room).name} --steps {args.steps} --warmup {args.warmup}` "
             f"({os.cpu_count()} CPUs): {wall * ms:.1f} ms per step, {sum(busy.values()):.2f} cores busy", "",
             "| thread | share of the wall time on a CPU |", "| --- | ---: |"]
    lines += [f"| {name} | {share:.2f} |" for name, share in sorted(busy.items(), key=lambda kv: -kv[1])]
    lines += ["", "| the training thread's wall time | ms per step | share |", "| --- | ---: | ---: |"]
    for label, seconds in (("its block of a split convolution", clock.own),
                           ("waiting for the helper's block after it", clock.wait),
                           ("convolutions that run whole (small maps)", clock.whole),
                           ("everything else (the helper idle)", rest)):
        lines.append(f"| {label} | {seconds * ms:.1f} | {seconds / wall:.2f} |")
    print_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
