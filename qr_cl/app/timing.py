"""The one timing helper of the application and the benchmarks: wall times of calls (after
warm-up), the minor page faults they cost and the peak host memory they touched.

Standard library only: ``bench/`` scripts that measure another install of qr-cl load this file
by path (``bench/benchutil.py``).
"""
from __future__ import annotations

import os
import resource
import statistics
import threading
import time
from typing import Callable, TypeVar

T = TypeVar("T")


def _rss_bytes() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


class PeakMemory:
    """Peak resident host memory above the level at entry, sampled every 2 ms in a thread."""

    def __enter__(self) -> "PeakMemory":
        self.base = self.peak = _rss_bytes()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.wait(0.002):
            self.peak = max(self.peak, _rss_bytes())

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss_bytes())

    @property
    def above_base(self) -> int:
        return self.peak - self.base


class Stopwatch:
    """Wall seconds since it was made (``time.perf_counter``)."""

    def __init__(self) -> None:
        self.start = time.perf_counter()

    @property
    def seconds(self) -> float:
        """Wall seconds since the stopwatch was made."""
        return time.perf_counter() - self.start


def timed(call: Callable[[], T]) -> tuple[T, float]:
    """(``call()``'s result, the wall seconds it took)."""
    watch = Stopwatch()
    result = call()
    return result, watch.seconds


def minor_faults() -> int:
    """This process's minor page faults so far (``ru_minflt``): a fresh allocation's pages each
    cost one when first touched."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def timed_calls(call: Callable[[], object], calls: int) -> tuple[list[float], list[int]]:
    """Wall seconds [calls] and minor page faults [calls] of each of ``calls`` calls of ``call()``."""
    times, faults = [], []
    for _ in range(calls):
        faults_before, watch = minor_faults(), Stopwatch()
        call()
        times.append(watch.seconds)
        faults.append(minor_faults() - faults_before)
    return times, faults


def measure(fn: Callable[[], object], rounds: int, warmup: int = 1) -> dict:
    """Timings of ``fn()`` (which must finish its queue) after ``warmup`` calls: min, median,
    spread (max - min) and every round's time in s, and the peak host bytes above the start."""
    for _ in range(warmup):
        fn()
    with PeakMemory() as mem:
        times, _ = timed_calls(fn, rounds)
    return {"min_s": min(times), "median_s": statistics.median(times),
            "spread_s": max(times) - min(times), "rounds": rounds, "times_s": times,
            "peak_host_bytes": mem.above_base}


def warm_page_faults(call: Callable[[], object], calls: int = 2) -> float:
    """Minor page faults per call of ``call()`` after a warm-up call: what fresh allocations cost a
    warm call (glibc maps allocations above 32 MB freshly each time)."""
    call()
    _, faults = timed_calls(call, calls)
    return sum(faults) / calls
