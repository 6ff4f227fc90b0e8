"""Shared timing helper of the benchmark scripts."""
from __future__ import annotations

import statistics
import time
from typing import Callable


def median_times(fn: Callable[[], object], reps: int, warmup: int = 1) -> tuple[float, float]:
    """``(wall s, CPU s)``: median wall time and median process CPU time (all threads) of ``fn`` over
    ``reps`` calls after ``warmup`` untimed ones. On a busy machine CPU seconds are the steadier figure:
    wall time also counts the time other processes hold the cores."""
    for _ in range(warmup):
        fn()
    wall, cpu = [], []
    for _ in range(reps):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)
