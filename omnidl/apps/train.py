"""``omnidl train`` (and the checkout's ``python train.py``): train a model with the Hydra config tree shipped in
the package (``omnidl/configs``, :func:`omnidl.engine.config.config_root`)::

    omnidl train model=fredsnet [group=option ...] [key=value ...]      # = python train.py model=fredsnet ...
    omnidl train +search=fredsnet_loss_weights                          # an Ax loss-weight search

Every Hydra option works as with ``@hydra.main`` (``-m`` sweeps, ``--cfg job``, ``hydra.run.dir=...``); the run
folder is ``outputs/<date>/<time>/`` under the current directory. Under ``torchrun --nproc_per_node=N`` every rank
shares one run dir (:func:`omnidl.engine.launch.prepare_argv`). A config holding a non-finite number (``nan``,
``inf``) is refused before anything is built (:func:`omnidl.engine.config.check_finite_config`).
"""
from __future__ import annotations

import sys
from collections.abc import Sequence

import hydra
from omegaconf import DictConfig

from omnidl.engine.config import check_finite_config, config_root, register_configs
from omnidl.engine.launch import prepare_argv


@hydra.main(version_base="1.3", config_path=str(config_root()), config_name="train")
def _run(cfg: DictConfig) -> float | None:
    try:
        check_finite_config(cfg)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    if cfg.get("search"):  # +search=<name>: an Ax loss-weight search of short training runs
        from omnidl.search import run_search_from_config
        return run_search_from_config(cfg).best_objective
    from omnidl.engine import train
    from omnidl.engine.interrupt import TrainingInterrupted
    from omnidl.utils.outputs import OUTPUT_ERRORS
    try:
        summary = train(cfg)
    except TrainingInterrupted as e:  # Ctrl-C / SIGTERM: last.pt written, the resume command logged
        sys.exit(e.exit_code)
    except OUTPUT_ERRORS as e:        # a used run folder, a run folder another process holds
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    return summary.get("best")  # the optimised value, for Hydra sweepers


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> int:
    """Run Hydra's train app on ``argv`` (default ``sys.argv[1:]``; Hydra reads ``sys.argv``, which is set to
    ``[prog, *argv]`` when ``argv`` is given). Returns 0 (errors exit through ``SystemExit``)."""
    if argv is not None:
        sys.argv = [prog or sys.argv[0], *argv]
    register_configs()
    prepare_argv()
    _run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
