"""The run folder of ``train.py`` and ``evaluate.py`` under the output policy (:mod:`omnidl.utils.outputs`).

Training (:func:`check_train_dir`, called by :func:`omnidl.engine.train` while it holds the folder's
:class:`~omnidl.utils.outputs.RunLock`):

* a folder that holds a previous run's results (:data:`TRAIN_RESULTS`: ``checkpoints/last.pt``, ``best.pt``,
  ``metrics.json``, ``train_log.jsonl``) is refused unless the run resumes it (``trainer.resume=true``; its own
  ``last.pt``) or ``trainer.overwrite=true`` is given (then those files are deleted first, with a warning);
* ``trainer.resume=true`` in such a folder without ``checkpoints/last.pt`` stops (nothing to continue, and
  starting over would replace the results) instead of silently restarting; in an empty folder it starts from
  scratch, as before;
* ``checkpoint=PATH`` (weights to start from) into a used folder needs ``trainer.overwrite=true`` too, unless
  ``PATH`` is the folder's own ``last.pt`` with ``trainer.resume=true``.

Evaluation (:func:`evaluation_dir`): ``evaluate.py`` never replaces a training run's files. Into a training run
folder (one with ``checkpoints/`` or ``train_log.jsonl``) it writes under ``eval_<checkpoint stem>_<split>/``
(e.g. ``eval_best_test/``); a folder that already holds an evaluation's results (:data:`EVAL_RESULTS`) is refused
unless ``trainer.overwrite=true``. Hydra's own ``.hydra/`` files: when ``hydra.run.dir=`` names a folder that
already has ``.hydra/config.yaml``, :func:`omnidl.engine.launch.prepare_argv` (run before ``@hydra.main``)
redirects this command's copy to ``.hydra/<script>-<time>_<pid>/``, so the training run's own
``.hydra/config.yaml`` is never rewritten.

``trainer.val_max_batches=0`` is refused up front (:func:`check_output_options`): it would validate nothing and
fail only at the end. To train without validation, use a data config without a ``val`` split (checkpoints are
still written at every epoch end / ``trainer.ckpt_every_steps``).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from omnidl.utils.outputs import OutputExistsError

log = logging.getLogger("omnidl.engine")

#: the files that make a folder a (started or finished) training run's
TRAIN_RESULTS = ("checkpoints/last.pt", "checkpoints/best.pt", "metrics.json", "train_log.jsonl")
#: the files an evaluation writes at the top of its folder (pictures go to sub-folders named per sample)
EVAL_RESULTS = ("metrics.json", "per_image.csv", "per_image.json", "rotation.csv", "rotation.png",
                "postprocess.jsonl", "report.html")
OVERWRITE = "trainer.overwrite=true"


def overwrite_of(cfg: DictConfig) -> bool:
    """``trainer.overwrite`` (false when the schema has no such key)."""
    tc = cfg.get("trainer") or {}
    value = tc.get("overwrite", False)
    if not isinstance(value, bool):
        raise ValueError(f"trainer.overwrite={value!r}: expected true or false")
    return value


def check_output_options(tc: Any) -> None:
    """Trainer values that would only fail at the end of a run: ``ValueError`` naming the key and value."""
    vmb = int(tc.get("val_max_batches", -1))
    if vmb == 0 or vmb < -1:
        raise ValueError(f"trainer.val_max_batches={tc.val_max_batches!r}: expected -1 (the whole validation set) or "
                         "a positive number of batches; 0 would validate nothing and the run would fail at its end. "
                         "To train without validation, use a data config without a 'val' split (last.pt and "
                         "best.pt are then written at every epoch end)")


def train_results(out_dir: str | Path) -> list[Path]:
    """The :data:`TRAIN_RESULTS` files present in ``out_dir``."""
    out = Path(out_dir)
    return [out / name for name in TRAIN_RESULTS if (out / name).exists()]


def clear_train_results(out_dir: str | Path, reason: str) -> list[Path]:
    """Delete the :data:`TRAIN_RESULTS` files of ``out_dir`` (logged with ``reason``); returns them."""
    removed = []
    for p in train_results(out_dir):
        p.unlink()
        removed.append(p)
    if removed:
        log.warning("%s: removed the previous run's %s", reason, ", ".join(str(p) for p in removed))
    return removed


def check_train_dir(cfg: DictConfig, out_dir: str | Path, last: Path) -> None:
    """Apply the training rules of the module docstring to ``out_dir`` (whose ``last.pt`` is ``last``)."""
    out = Path(out_dir)
    used = train_results(out)
    if not used:
        return
    tc = cfg.trainer
    resume, overwrite = bool(tc.resume), overwrite_of(cfg)
    ckpt = cfg.get("checkpoint")
    shown = ", ".join(p.relative_to(out).as_posix() for p in used)
    if resume and not ckpt:
        if last.is_file():
            return                       # continue this run
        if not overwrite:
            raise ValueError(f"trainer.resume=true but {out} has no checkpoints/last.pt to continue from, although it "
                             f"holds a previous run's files ({shown}); starting over would replace them. Add "
                             f"{OVERWRITE} to start a new run in this folder, or choose another folder "
                             "(hydra.run.dir=...)")
    elif resume and ckpt and last.is_file() and Path(str(ckpt)).resolve() == last.resolve():
        return                           # checkpoint=<this run's last.pt> trainer.resume=true
    elif not overwrite:
        start = f"starting from checkpoint={ckpt} " if ckpt else ""
        raise OutputExistsError(f"{out} already holds a training run ({shown}); {start}here would overwrite its "
                                "checkpoints and metrics. Add trainer.resume=true to continue that run, "
                                f"{OVERWRITE} to replace it, or choose another folder (hydra.run.dir=...)")
    clear_train_results(out, f"{OVERWRITE} in {out}")


def is_training_run(folder: str | Path) -> bool:
    """Whether ``folder`` is a training run's (``checkpoints/``, ``train_log.jsonl`` or a training ``metrics.json``)."""
    folder = Path(folder)
    if (folder / "checkpoints").is_dir() or (folder / "train_log.jsonl").exists():
        return True
    try:
        m = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(m, dict) and "monitor" in m and "checkpoint_last" in m


def _safe(text: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in text).strip(".") or "_"


def evaluation_dir(cfg: DictConfig, out_dir: str | Path) -> Path:
    """Where ``evaluate`` writes: ``out_dir``, or ``out_dir/eval_<checkpoint stem>_<split>`` when ``out_dir`` is a
    training run's folder (finished or still training)."""
    out = Path(out_dir)
    if not is_training_run(out):
        return out
    ck = cfg.get("checkpoint")
    stem = _safe(Path(str(ck)).stem) if ck else "untrained"
    split = _safe(str((cfg.get("eval") or {}).get("split", "test")))
    sub = out / f"eval_{stem}_{split}"
    log.info("%s is a training run's folder: the evaluation goes to %s (the run's metrics.json and .hydra/ are left "
             "as they are)", out, sub)
    return sub


def check_evaluation_dir(cfg: DictConfig, out_dir: str | Path) -> None:
    """``OutputExistsError`` when ``out_dir`` already holds an evaluation's results (:data:`EVAL_RESULTS`) or is a
    training run's folder, unless ``trainer.overwrite=true`` (never for a training folder)."""
    out = Path(out_dir)
    if is_training_run(out):
        raise OutputExistsError(f"{out} is a training run's folder; an evaluation never writes into it (its "
                                "metrics.json would be replaced)")
    done = [name for name in EVAL_RESULTS if (out / name).exists()]
    if done and not overwrite_of(cfg):
        raise OutputExistsError(f"{out} already holds an evaluation ({', '.join(done)}); add {OVERWRITE} to replace "
                                "it, or choose another folder (hydra.run.dir=...)")
