"""The one timing helper of the benchmarks: wall times of a call (after warm-up) and the peak
host memory it touched."""
from __future__ import annotations

import os
import statistics
import threading
import time



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


def measure(fn, rounds: int, warmup: int = 1) -> dict:
    """Timings of ``fn()`` (which must finish its queue): min, median, spread (max - min) in s."""
    for _ in range(warmup):
        fn()
    times = []
    with PeakMemory() as mem:
        for _ in range(rounds):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
    return {"min_s": min(times), "median_s": statistics.median(times),
            "spread_s": max(times) - min(times), "rounds": rounds, "times_s": times,
            "peak_host_bytes": mem.above_base}
