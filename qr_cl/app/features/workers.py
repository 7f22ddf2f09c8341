"""``qr-cl features --workers N``: frames in N worker processes.

Each worker is a fresh Python (the spawn start method: torch's threads and devices do not survive
a fork) that loads the models once from the weights files (:class:`WorkerSetup` carries paths and
settings, not models), then takes whole frames from the main process one at a time over its own
pipe and writes each frame's files itself, atomically (:func:`.store.write_frame`). The main
process hands out the frames and counts those finished. A worker's :class:`FeaturesError` (an
unreadable image) stops the run with that one line; so does a worker that dies (killed, out of
memory). Stopping (Ctrl-C, an error) terminates the workers: a frame killed mid-write leaves no
file in place, at most a temporary one that the next run removes, so only whole frames remain.
Workers ignore Ctrl-C; the main process stops them.
"""
from __future__ import annotations

import multiprocessing
import signal
import traceback
from collections import deque
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Iterator

from ...scene import Camera
from .errors import FeaturesError
from .masks import MaskSettings

#: One frame: its camera, image file and file stem.
Frame = tuple[Camera, Path, str]


@dataclass(frozen=True)
class WorkerSetup:
    """What a worker needs to build its models and write frames (picklable)."""

    clip_weights: str
    clip_model: str | None
    sam_weights: str
    device: str
    threads: int
    settings: MaskSettings
    batch: int
    folder: Path


def worker_threads(total: int, workers: int) -> int:
    """Torch threads of each of ``workers`` processes sharing ``total``: an even share, at least 1."""
    return max(1, total // workers)


def _serve(conn: Connection, setup: WorkerSetup) -> None:
    """A worker's life: load the models, then take frames until told to stop (``None``) or the
    main process is gone. Replies ``("done", stem, masks)``, ``("error", message)`` for a
    FeaturesError or ``("crash", traceback)``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        import torch

        from .clip_model import load_clip
        from .frames import frame_features
        from .photos import read_image
        from .sam_model import load_sam
        from .store import write_frame

        from ..process import keep_freed_memory

        keep_freed_memory()
        torch.set_num_threads(setup.threads)
        device = torch.device(setup.device)
        clip = load_clip(setup.clip_weights, setup.clip_model).to(device)
        sam = load_sam(setup.sam_weights).to(device)
        while (task := conn.recv()) is not None:
            camera, path, stem = task
            result = frame_features(sam, clip, read_image(path, camera), setup.settings, setup.batch)
            write_frame(setup.folder, stem, result.ids, result.features)
            conn.send(("done", stem, sum(result.counts)))
    except (EOFError, BrokenPipeError):                    # the main process is gone: nothing to tell
        return
    except FeaturesError as exc:
        conn.send(("error", str(exc)))
    except BaseException:
        conn.send(("crash", traceback.format_exc()))


class WorkerPool:
    """``workers`` processes running :func:`_serve` with ``setup``; a context manager that
    terminates any still running on exit."""

    def __init__(self, setup: WorkerSetup, workers: int):
        self.setup = setup
        context = multiprocessing.get_context("spawn")
        self.processes: dict[Connection, multiprocessing.process.BaseProcess] = {}
        #: The stem of the frame each busy worker is on, by its pipe.
        self.in_flight: dict[Connection, str] = {}
        try:
            for _ in range(workers):
                mine, theirs = context.Pipe()
                process = context.Process(target=_serve, args=(theirs, setup), daemon=True,
                                          name="qr-cl features worker")
                process.start()
                theirs.close()                              # so that the worker's death reads as EOF
                self.processes[mine] = process
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Terminate the workers still running (a frame in flight leaves no file in place)."""
        for process in self.processes.values():
            if process.is_alive():
                process.terminate()
        for conn, process in self.processes.items():
            process.join(5)
            if process.is_alive():
                process.kill()
                process.join()
            conn.close()
        self.processes, self.in_flight = {}, {}

    def _died(self, conn: Connection, stem: str) -> FeaturesError:
        process = self.processes[conn]
        process.join(5)
        code = process.exitcode
        how = (f"killed by {signal.Signals(-code).name}" if code is not None and code < 0
               and -code in signal.valid_signals() else f"exit status {code}")
        return FeaturesError(f"{self.setup.folder}: a worker process died on frame {stem} ({how}; out of memory?); "
                             f"the frames written are kept: run again to go on")

    def frames(self, work: list[Frame]) -> Iterator[tuple[str, int]]:
        """Process ``work``, a frame per idle worker at a time; yields (stem, masks) of each frame
        as it is written, in the order they finish. Raises the first worker's FeaturesError, a
        FeaturesError for a worker that died, or RuntimeError with a worker's traceback."""
        pending = deque(work)
        busy = self.in_flight

        def hand_out(conn: Connection) -> None:
            task = pending.popleft() if pending else None
            try:
                conn.send(task)
            except (BrokenPipeError, ConnectionResetError):
                if task is not None:
                    raise self._died(conn, task[2]) from None
                return
            if task is not None:
                busy[conn] = task[2]

        for conn in list(self.processes):
            hand_out(conn)
        while busy:
            for conn in wait(list(busy)):
                stem = busy.pop(conn)
                try:
                    reply = conn.recv()
                except (EOFError, ConnectionResetError):
                    raise self._died(conn, stem) from None
                if reply[0] == "error":
                    raise FeaturesError(reply[1])
                if reply[0] == "crash":
                    raise RuntimeError(f"a qr-cl features worker failed on frame {stem}:\n{reply[1]}")
                yield reply[1], reply[2]
                hand_out(conn)
