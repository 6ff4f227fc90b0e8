"""Seeds, thread counts and RNG snapshots (for exact resume)."""
from __future__ import annotations

import logging
import random
import statistics
import time
from typing import Any

import numpy as np
import torch

from omnidl.utils import threads as _threads

from .config import check_num_threads

log = logging.getLogger("omnidl.engine")

#: torch's intra-op thread count when omnidl was imported: ``num_threads=0`` restores it, so a job of a
#: multirun does not inherit the previous job's setting
_INITIAL_THREADS = torch.get_num_threads()


def auto_num_threads(samples: int = 5, interval_s: float = 0.05) -> tuple[int, dict[str, float]]:
    """The intra-op thread count for ``num_threads=auto``: torch's default count (:data:`_INITIAL_THREADS`)
    when every one of those threads has a free CPU, else one per free CPU (at least 1).

    The load is the number of tasks running or waiting for a CPU
    (:func:`omnidl.utils.threads.runnable_tasks`, the median of ``samples`` readings ``interval_s`` apart);
    one of them is this process's own thread reading it, the rest are the other tasks. Free CPUs = usable
    CPUs - other tasks. On an oversubscribed machine every multi-threaded op's OpenMP fork/join waits for a
    descheduled thread, which can make a step many times slower than with fewer threads.

    Returns ``(threads, basis)`` where ``basis`` has the numbers it was decided on (for the log).
    """
    readings = []
    for i in range(max(1, samples)):
        if i:
            time.sleep(interval_s)
        readings.append(float(_threads.runnable_tasks()))
    runnable = statistics.median(readings)
    cpus = _threads.usable_cpus()
    others = max(0.0, runnable - 1.0)
    free = cpus - others
    base = max(1, _INITIAL_THREADS)
    n = base if free >= base else max(1, int(free))
    return n, {"runnable": runnable, "others": others, "cpus": float(cpus), "free": free, "default": float(base)}


def resolve_num_threads(num_threads: Any, key: str = "trainer.num_threads") -> int:
    """The intra-op thread count for a ``num_threads`` setting: ``"auto"`` -> :func:`auto_num_threads` (the
    choice and its basis are logged), ``0`` -> torch's default count when omnidl was imported, ``N`` -> N.
    A bad value is a ``ValueError`` naming ``key`` (:func:`omnidl.engine.config.check_num_threads`)."""
    value = check_num_threads(num_threads, key)
    if value == "auto":
        n, b = auto_num_threads()
        log.info("%s=auto: %d intra-op thread%s (load: %g runnable tasks, so %g besides this process, on %d usable "
                 "CPUs; torch's default %d)", key, n, "" if n == 1 else "s", b["runnable"], b["others"],
                 int(b["cpus"]), int(b["default"]))
        return n
    return int(value) if int(value) > 0 else _INITIAL_THREADS


def seed_everything(seed: int, num_threads: int | str = 0, deterministic: bool = False) -> int:
    """Reset Python, NumPy and torch RNGs (and CUDA's) to ``seed``; set torch's intra-op thread count
    (:func:`resolve_num_threads`: ``"auto"`` from the machine's load, ``0`` the count torch had when this
    module was imported, ``N`` N threads). Returns the thread count set.

    Called at the start of every job: Hydra's basic multirun launcher runs jobs in one process,
    so nothing may leak from the previous job.
    """
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    if torch.cuda.is_available():
        torch.cuda.manual_seed_all(seed)
    n = resolve_num_threads(num_threads)
    torch.set_num_threads(n)
    torch.use_deterministic_algorithms(deterministic, warn_only=True)
    return n


def rng_state() -> dict[str, Any]:
    """A snapshot of every global RNG (Python, NumPy, torch CPU, CUDA), made only of tensors, numbers, strings
    and tuples, so a checkpoint holding it loads with ``torch.load(weights_only=True)``."""
    name, keys, pos, has_gauss, gauss = np.random.get_state()
    numpy_state = (name, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss), float(gauss))
    state = {"python": random.getstate(), "numpy": numpy_state, "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore a snapshot made by :func:`rng_state`."""
    random.setstate(state["python"])
    name, keys, *rest = state["numpy"]
    keys = keys.numpy() if isinstance(keys, torch.Tensor) else np.asarray(keys)  # older checkpoints: an array
    np.random.set_state((name, keys.astype(np.uint32), *rest))
    torch.set_rng_state(state["torch"].cpu() if hasattr(state["torch"], "cpu") else state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
