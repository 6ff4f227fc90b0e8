"""Command-line preparation for the entry points (runs before ``@hydra.main``)."""
from __future__ import annotations

import os
import sys
import time


def prepare_argv(argv: list[str] | None = None) -> list[str]:
    """Under ``torchrun`` (``WORLD_SIZE`` > 1) give every rank the same Hydra run dir and let only rank 0
    write Hydra's ``.hydra/`` folder and log file.

    Each rank would otherwise evaluate ``${now:...}`` itself (racy). The shared dir is
    ``outputs/torchrun/<date>/<TORCHELASTIC_RUN_ID or agent pid>`` unless ``hydra.run.dir=...`` is given. Edits ``sys.argv``
    in place (and returns it).
    """
    argv = sys.argv if argv is None else argv
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
