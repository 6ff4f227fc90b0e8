"""Command-line preparation for the entry points (runs before ``@hydra.main``)."""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path


def prepare_argv(argv: list[str] | None = None, task: str = "train") -> list[str]:
    """Edit ``argv`` (``sys.argv`` by default) in place before ``@hydra.main`` runs, and return it:

    * **an existing run folder's** ``.hydra/``: when ``hydra.run.dir=DIR`` names a folder that already has
      ``.hydra/config.yaml`` (resuming a run, evaluating into a training folder, a refused second start), this
      command's Hydra files go to ``DIR/.hydra/<task>-<time>_<pid>/`` (``hydra.output_subdir``), so Hydra never
      rewrites the original run's ``config.yaml``, ``hydra.yaml`` and ``overrides.yaml`` (unless
      ``hydra.output_subdir=`` is given). ``task``: ``train`` or ``evaluate`` (the calling app).
    * **torchrun** (``WORLD_SIZE`` > 1): every rank gets the same Hydra run dir and only rank 0 writes Hydra's
      ``.hydra/`` folder and log file. Each rank would otherwise evaluate ``${now:...}`` itself (racy). The shared
      dir is ``outputs/torchrun/<date>/<TORCHELASTIC_RUN_ID or agent pid>`` unless ``hydra.run.dir=...`` is given.
    """
    argv = sys.argv if argv is None else argv
    if int(os.environ.get("RANK", "0")) == 0:  # (other torchrun ranks write no Hydra files: below)
        _keep_existing_hydra_files(argv, task)
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return argv
    args = argv[1:]
    if not any(a.startswith(("hydra.run.dir=", "++hydra.run.dir=")) for a in args):
        run_id = os.environ.get("TORCHELASTIC_RUN_ID", "none")
        if run_id in ("", "none"):  # not --standalone: the torchrun agent (our parent) is shared by local ranks
            run_id = f"agent{os.getppid()}"
        argv.append(f"hydra.run.dir=outputs/torchrun/{time.strftime('%Y-%m-%d')}/{run_id}")
    if int(os.environ.get("RANK", "0")) != 0:
        argv.extend(["hydra.output_subdir=null", "hydra/job_logging=disabled", "hydra/hydra_logging=disabled"])
    return argv


def _keep_existing_hydra_files(argv: list[str], task: str) -> None:
    """Add ``hydra.output_subdir=.hydra/<task>-<stamp>`` when ``hydra.run.dir`` already holds ``.hydra/config.yaml``."""
    args = argv[1:]
    if any(a.lstrip("+").startswith("hydra.output_subdir=") for a in args):
        return
    run_dirs = [a.split("=", 1)[1] for a in args if a.lstrip("+").startswith("hydra.run.dir=")]
    if not run_dirs:
        return
    folder = Path(run_dirs[-1].strip("'\""))
    if not (folder / ".hydra" / "config.yaml").is_file():
        return
    stamp = f"{time.strftime('%Y-%m-%d_%H-%M-%S')}_{os.getpid()}"
    argv.append(f"hydra.output_subdir=.hydra/{task}-{stamp}")
