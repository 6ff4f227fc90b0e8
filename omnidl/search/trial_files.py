"""What a finished search trial keeps on disk (``search.keep_checkpoints``).

A trial is a full training run: by default the engine leaves ``checkpoints/last.pt`` and ``best.pt`` with
the optimiser state (about 3x the weights each), so a 6-trial tiny search used 1.6 GB. The search only
needs each trial's metrics; the weights are kept for looking at a trial afterwards:

* ``best_trial`` (default): every trial keeps ``metrics.json`` and its logs; the best trial so far also
  keeps a weights-only ``checkpoints/best.pt`` (``model``, ``config``, ``step``, ``epoch``, ``best``);
* ``weights``: every trial keeps a weights-only ``best.pt``; ``last.pt`` is removed;
* ``none``: metrics and logs only, no checkpoint;
* ``all``: everything the engine wrote (to resume or fine-tune a trial).
"""
from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)

KEEP_CHOICES = ("weights", "best_trial", "none", "all")
#: the entries of an engine checkpoint a weights-only copy keeps
WEIGHTS_KEYS = ("model", "config", "step", "epoch", "best", "best_step")


def check_keep(value: object) -> str:
    """``value`` if it is one of :data:`KEEP_CHOICES`, else a ``ValueError`` naming the field."""
    if value not in KEEP_CHOICES:
        raise ValueError(f"search.keep_checkpoints: expected one of {list(KEEP_CHOICES)}, got {value!r}")
    return str(value)


def weights_only(path: Path) -> None:
    """Rewrite the checkpoint ``path`` (atomically) without optimiser/scheduler/scaler/RNG state."""
    from omnidl.engine.checkpoint import load_checkpoint, save_checkpoint
    ck = load_checkpoint(path)
    if set(ck) <= set(WEIGHTS_KEYS) | {"version"}:
        return
    save_checkpoint(path, {k: ck[k] for k in WEIGHTS_KEYS if k in ck})


def prune_trial(trial_dir: Path, keep: str) -> None:
    """Apply ``keep`` (see the module docstring) to a finished trial's folder."""
    ckdir = Path(trial_dir) / "checkpoints"
    if keep == "all" or not ckdir.is_dir():
        return
    for p in ckdir.glob(".*.tmp"):  # orphans of an interrupted write
        p.unlink(missing_ok=True)
    (ckdir / "last.pt").unlink(missing_ok=True)
    best = ckdir / "best.pt"
    if keep == "none":
        best.unlink(missing_ok=True)
    elif best.exists():
        weights_only(best)


def drop_other_bests(search_dir: Path, best_trial_dir: Path) -> None:
    """``best_trial``: remove ``best.pt`` from every trial folder but ``best_trial_dir``."""
    for p in Path(search_dir).glob("trial_*/checkpoints/best.pt"):
        if p.parent.parent.resolve() != Path(best_trial_dir).resolve():
            p.unlink(missing_ok=True)


def dir_size(path: Path) -> int:
    """Bytes under ``path`` (files only)."""
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())
