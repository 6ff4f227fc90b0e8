"""Shared timing helpers of the benchmark scripts: medians, interleaved A/B timing, load reporting.

Rules every benchmark follows (issue 17, item 7): each target is printed as a figure AND a ratio to a
baseline measured in the same run (interleaved, so that a change of machine load hits both alike), and
the 1-minute load average is printed with a flag when it exceeds the benchmark's own threads (then
absolute times are not comparable with anything; ratios are less affected but still noisy).
"""
from __future__ import annotations

import os
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


def load1() -> float:
    """1-minute load average (``nan`` where the platform has none)."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return float("nan")


def load_line(threads: int, what: str = "") -> str:
    """``# load average ... (own threads N)`` plus a LOADED flag when the load exceeds ``threads``."""
    la = load1()
    flag = "" if la <= threads else (f"  ** LOADED: load {la:.2f} > {threads} own threads: absolute figures "
                                     "are not comparable; ratios are noisy **")
    return f"# load average (1 min) {la:.2f}{' ' + what if what else ''}, own threads {threads}{flag}"


def host_line() -> str:
    """``# host: CPU model, CPUs, L2 per core, omnidl's native kernel``: figures differ between hosts (an AVX-512
    host runs oneDNN's convolutions about twice as fast as an AVX2 one), so each run names its own."""
    from omnidl.nn import fused, native
    model = "unknown CPU"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    l2 = fused.l2_cache_bytes()
    st = native.status()
    kernel = st["kernel"] or "unavailable: " + st["reason"]
    return (f"# host: {model}, {os.cpu_count()} CPUs, L2 {l2 // 1024 if l2 else '?'} kB per core, omnidl native "
            f"kernel {kernel}")


def is_loaded(threads: int) -> bool:
    return load1() > threads


def interleaved(jobs: dict[str, Callable[[], object]], reps: int, warmup: int = 1,
                reps_of: dict[str, int] | None = None) -> dict[str, list[float]]:
    """Wall seconds of every job, one call of each per repetition (order alternated every repetition),
    after ``warmup`` untimed rounds. ``reps_of`` caps the repetitions of slow jobs (e.g. a baseline)."""
    for _ in range(warmup):
        for fn in jobs.values():
            fn()
    times: dict[str, list[float]] = {k: [] for k in jobs}
    names = list(jobs)
    for r in range(reps):
        for k in (names if r % 2 == 0 else names[::-1]):
            if reps_of and k in reps_of and len(times[k]) >= reps_of[k]:
                continue
            t0 = time.perf_counter()
            jobs[k]()
            times[k].append(time.perf_counter() - t0)
    return times


def ratio(times: dict[str, list[float]], a: str, b: str) -> float:
    """Median of per-repetition ratios ``a / b`` over the repetitions both have (ratio of medians if the
    counts differ)."""
    ta, tb = times[a], times[b]
    n = min(len(ta), len(tb))
    if len(ta) == len(tb):
        return statistics.median(x / y for x, y in zip(ta, tb))
    return statistics.median(ta[:n] if n else ta) / statistics.median(tb[:n] if n else tb)


def target_line(name: str, figure: str, ratio_value: float, baseline: str, target: str | None = None,
                ok: bool | None = None, loaded: bool = False) -> str:
    """One printed target: ``name: figure = ratio x baseline (target ...: met/MISSED) [loaded]``."""
    s = f"TARGET {name}: {figure} = {ratio_value:.2f}x {baseline}"
    if target is not None:
        s += f" (target {target}: {'met' if ok else 'MISSED'})"
    if loaded:
        s += " [taken under load]"
    return s
