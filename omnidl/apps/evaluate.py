"""``omnidl evaluate`` (and the checkout's ``python evaluate.py``): evaluate a checkpoint with the Hydra config
tree shipped in the package (``omnidl/configs``)::

    omnidl evaluate model=fredsnet checkpoint=PATH [data=folder data.root=DIR]   # = python evaluate.py ...

Writes metrics, per-image records, pictures and point clouds (:mod:`omnidl.engine.evaluator`), then the
static page ``report.html`` over them (:mod:`omnidl.apps.html_report`), in ``outputs/<date>/<time>/`` under the
current directory (or ``hydra.run.dir=...``). A config holding a non-finite number is refused before anything
is built (:func:`omnidl.engine.config.check_finite_config`).
"""
from __future__ import annotations

import sys
from collections.abc import Sequence

import hydra
from omegaconf import DictConfig

from omnidl.engine.config import check_finite_config, config_root, register_configs
from omnidl.engine.launch import prepare_argv


@hydra.main(version_base="1.3", config_path=str(config_root()), config_name="evaluate")
def _run(cfg: DictConfig) -> None:
    try:
        check_finite_config(cfg)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    from omnidl.apps.html_report import write_report
    from omnidl.engine import evaluate
    from omnidl.utils.outputs import OUTPUT_ERRORS
    try:
        summary = evaluate(cfg)
    except OUTPUT_ERRORS as e:        # an earlier evaluation's results, a folder another process holds
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    print(f"report: {write_report(summary['output_dir'], overwrite=True)}")   # the evaluation's own folder


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> int:
    """Run Hydra's evaluate app on ``argv`` (default ``sys.argv[1:]``; see :func:`omnidl.apps.train.main`)."""
    if argv is not None:
        sys.argv = [prog or sys.argv[0], *argv]
    register_configs()
    prepare_argv(task="evaluate")
    _run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
