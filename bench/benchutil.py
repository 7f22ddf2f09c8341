"""Helpers shared by the benchmarks (imported by name: bench/ is on sys.path under pytest)."""
from __future__ import annotations


def run(benchmark, fn, full: bool, rounds: int = 5):
    """Time ``fn`` (which must finish its OpenCL queue) with warm-up in full mode, once in smoke."""
    return benchmark.pedantic(fn, rounds=rounds if full else 1, iterations=1,
                              warmup_rounds=1 if full else 0)
