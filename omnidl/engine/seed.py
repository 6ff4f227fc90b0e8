"""Seeds, thread counts and RNG snapshots (for exact resume)."""
from __future__ import annotations

import random
from typing import Any

import numpy as np
import torch

#: torch's intra-op thread count when omnidl was imported: ``num_threads=0`` restores it, so a job of a
#: multirun does not inherit the previous job's setting
_INITIAL_THREADS = torch.get_num_threads()


def seed_everything(seed: int, num_threads: int = 0, deterministic: bool = False) -> None:
    """Reset Python, NumPy and torch RNGs (and CUDA's) to ``seed``; set torch's intra-op thread count
    (``num_threads=0``: the count torch had when this module was imported).

    Called at the start of every job: Hydra's basic multirun launcher runs jobs in one process,
    so nothing may leak from the previous job.
    """
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    if torch.cuda.is_available():
        torch.cuda.manual_seed_all(seed)
    torch.set_num_threads(num_threads if num_threads > 0 else _INITIAL_THREADS)
    torch.use_deterministic_algorithms(deterministic, warn_only=True)


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
