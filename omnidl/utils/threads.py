"""Thread budget of op-count-bound CPU code (many small tensor ops).

Every multi-threaded ATen op is one OpenMP fork/join. For a path made of thousands of small ops
(the photometric gyroscope, the renderer's per-primitive work) the joins dominate: on a busy machine a
join waits until every worker thread has been scheduled again, so a 2-thread op on a shared core can take
milliseconds instead of microseconds. Running such a path with one intra-op thread removes the joins at
a small cost when the machine is idle (the ops are short); dense layers keep their own thread count.
"""
from __future__ import annotations

import contextlib
import os
from typing import Iterator, Union

import torch

Threads = Union[int, str, None]


def usable_cpus() -> int:
    """CPUs this process may run on (affinity mask where the platform has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def runnable_tasks() -> float:
    """Tasks running or waiting for a CPU right now (Linux ``/proc/loadavg`` field 4, this process's own
    threads included); elsewhere the 1-minute load average."""
    try:
        with open("/proc/loadavg") as f:
            return float(f.read().split()[3].split("/")[0])
    except (OSError, IndexError, ValueError):
        try:
            return os.getloadavg()[0]
        except (AttributeError, OSError):
            return 0.0


def auto_threads() -> int:
    """The process's intra-op threads when the machine has a free CPU for each, else 1: with the CPUs
    oversubscribed, every fork/join of a multi-threaded small op waits for a descheduled thread."""
    n = torch.get_num_threads()
    return 1 if runnable_tasks() > usable_cpus() else n


@contextlib.contextmanager
def limit_threads(n: Threads) -> Iterator[None]:
    """Run the block with at most ``n`` intra-op threads (``None`` or ``0``: unchanged; ``"auto"``:
    :func:`auto_threads`), then restore.

    The setting is per process for ATen's pool, so use it around code that does not run concurrently
    with other torch work in the same process.
    """
    if n == "auto":
        n = auto_threads()
    elif isinstance(n, str):
        raise ValueError(f"limit_threads: n must be an int, None or 'auto', got {n!r}")
    before = torch.get_num_threads()
    if not n or n >= before:
        yield
        return
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(before)
