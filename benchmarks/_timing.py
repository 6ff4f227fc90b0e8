"""Shared timing helpers of the benchmark scripts: medians, interleaved A/B timing, load reporting.

Rules every benchmark follows (issue 17, item 7): each target is printed as a figure AND a ratio to a
baseline measured in the same run (interleaved, so that a change of machine load hits both alike), and
the 1-minute load average is printed with a flag when it exceeds the benchmark's own threads (then
absolute times are not comparable with anything; ratios are less affected but still noisy). On a virtual
machine the load average misses the largest disturbance: the hypervisor running other guests on our
cores ("steal" time). One KVM host of issue 17 ran a register-only FMA loop at 41 to 134 GFLOP/s within
minutes with the load average below 1; so the share of CPU time stolen since the previous check is
printed and flagged as well (Linux ``/proc/stat``; absent elsewhere). It does not see everything either: other
guests' use of the shared caches and memory moved figures by a third on that host with no steal recorded.
"""
from __future__ import annotations

import os
import statistics
import time

import torch
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


#: steal share of the CPU time above which figures are flagged (one in ten cycles taken by other guests)
STEAL_FLAG = 0.10


def cpu_times(text: str | None = None) -> tuple[int, int] | None:
    """``(steal, total)`` clock ticks of all CPUs from ``/proc/stat``'s ``cpu`` line (``text``: its content,
    read from the file when ``None``); ``None`` where there is no such line. ``total`` sums user, nice,
    system, idle, iowait, irq, softirq and steal (guest time is already inside user and nice)."""
    if text is None:
        try:
            with open("/proc/stat") as f:
                text = f.read()
        except OSError:
            return None
    for line in text.splitlines():
        parts = line.split()
        if parts and parts[0] == "cpu":
            try:
                ticks = [int(v) for v in parts[1:9]]
            except ValueError:
                return None
            if len(ticks) < 8:
                return None
            return ticks[7], sum(ticks)
    return None


def steal_share(before: tuple[int, int] | None, after: tuple[int, int] | None) -> float | None:
    """Share of the CPU time between two :func:`cpu_times` readings that the hypervisor gave to other guests
    (``None`` without both readings or without elapsed ticks)."""
    if before is None or after is None or after[1] <= before[1]:
        return None
    return max(0, after[0] - before[0]) / (after[1] - before[1])


_clock = time.monotonic
#: (_clock(), cpu_times()) of every check, the first taken at import
_CHECKS: list[tuple[float, tuple[int, int] | None]] = [(_clock(), cpu_times())]


def steal_since_last(min_window: float = 1.0) -> float | None:
    """:func:`steal_share` since the latest previous check at least ``min_window`` seconds ago (the first
    check: this module's import), so that a line printed right after the check that closed a timed loop
    still reports that loop's window."""
    now = (_clock(), cpu_times())
    old = [c for c in _CHECKS if c[0] <= now[0] - min_window]
    share = steal_share((old[-1] if old else _CHECKS[0])[1], now[1])
    _CHECKS.append(now)
    del _CHECKS[1:-64]
    return share


def stolen(share: float | None) -> bool:
    """True when a steal share (:func:`steal_since_last`) exceeds :data:`STEAL_FLAG`."""
    return share is not None and share > STEAL_FLAG


def load1() -> float:
    """1-minute load average (``nan`` where the platform has none)."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return float("nan")


def load_line(threads: int, what: str = "") -> str:
    """``# load average ... (own threads N), hypervisor steal ...`` plus a LOADED flag when the load exceeds
    ``threads`` and a STOLEN flag when the steal share since the previous check (:func:`steal_since_last`)
    exceeds :data:`STEAL_FLAG`."""
    la = load1()
    steal = steal_since_last()
    flag = "" if la <= threads else (f"  ** LOADED: load {la:.2f} > {threads} own threads: absolute figures "
                                     "are not comparable; ratios are noisy **")
    if stolen(steal):
        flag += (f"  ** STOLEN: the hypervisor took {100 * steal:.0f} % of the CPU time: absolute figures are not "
                 "comparable; ratios are noisy **")
    shown = "" if steal is None else f", hypervisor steal {100 * steal:.1f} % since the last check"
    return f"# load average (1 min) {la:.2f}{' ' + what if what else ''}, own threads {threads}{shown}{flag}"


#: glibc's allocator settings read from the environment (``mallopt(3)``); ``GLIBC_TUNABLES``, PyTorch's
#: ``THP_MEM_ALLOC_ENABLE`` and a preloaded allocator are checked by :func:`allocator_tag` as well
ALLOCATOR_VARS = ("MALLOC_MMAP_MAX_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_",
                  "MALLOC_ARENA_MAX")


def allocator_tag(environ: dict[str, str] | None = None) -> str:
    """``""`` under glibc's default allocator, else `` [allocator: ...; the targets are judged on the default]``,
    appended to every :func:`target_line`. The benchmarks run on the default allocator; a run made otherwise
    must say so, because the allocator moves whole-model CPU times and the ratios between two models: a process
    that keeps freed memory (``MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=...``, a preloaded jemalloc, tcmalloc
    or mimalloc, glibc's malloc tunables) skips the page faults of freshly mapped large buffers, which glibc
    otherwise takes for every block above its mmap threshold, and PyTorch's ``THP_MEM_ALLOC_ENABLE=1`` takes
    one fault per 2 MB huge page instead of one per 4 kB page."""
    env = os.environ if environ is None else environ
    parts = [f"{k}={env[k]}" for k in ALLOCATOR_VARS if env.get(k)]
    if env.get("THP_MEM_ALLOC_ENABLE", "").strip() not in ("", "0"):       # PyTorch's own: huge pages for >= 2 MB
        parts.append(f"THP_MEM_ALLOC_ENABLE={env['THP_MEM_ALLOC_ENABLE']}")
    if "malloc" in env.get("GLIBC_TUNABLES", ""):
        parts.append(f"GLIBC_TUNABLES={env['GLIBC_TUNABLES']}")
    preload = os.path.basename(env.get("LD_PRELOAD", "").split(":")[0].split(" ")[0])
    if any(name in preload for name in ("jemalloc", "tcmalloc", "mimalloc")):
        parts.append(f"LD_PRELOAD={preload}")
    return f" [allocator: {' '.join(parts)}; the targets are judged on the default]" if parts else ""


def host_line() -> str:
    """``# host: CPU model, CPUs, L2 per core, the fixed-offset op's CPU kernel``: figures differ between hosts (an
    AVX-512 host runs oneDNN's convolutions about twice as fast as an AVX2 one), so each run names its own."""
    from omnidl.ops import _fixed_offset_cpu
    model = "unknown CPU"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    l2 = _fixed_offset_cpu.l2_cache_bytes()
    st = _fixed_offset_cpu.native_status()
    kernel = st["kernel"] or "unavailable: " + st["reason"]
    return (f"# host: {model}, {os.cpu_count()} CPUs, L2 {l2 // 1024 if l2 else '?'} kB per core, torch "
            f"{torch.__version__}, omnidl fixed-offset CPU kernel {kernel}")


def is_loaded(threads: int, steal: bool = True) -> bool:
    """True when the load exceeds ``threads`` or (``steal``) the steal share since the previous check exceeds
    :data:`STEAL_FLAG`. Benchmarks call it before their timed loop with ``steal=False`` (that window is the
    set-up: a plan built, a model warmed; steal there does not touch the figures) and after it with
    ``steal=True`` (the window is the timed loop)."""
    share = steal_since_last()          # always taken: it is also this check's snapshot
    return load1() > threads or (steal and stolen(share))


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
    return s + allocator_tag()
