"""Evaluate a checkpoint: ``python evaluate.py model=fredsnet checkpoint=PATH [data=folder data.root=DIR]``
(see docs/engine.md).

Writes metrics, per-image records, pictures and point clouds (:mod:`omnidl.engine.evaluator`), then the
static page ``report.html`` over them (:mod:`omnidl.apps.html_report`)."""
import hydra
from omegaconf import DictConfig

from omnidl.engine.config import register_configs

register_configs()


@hydra.main(version_base="1.3", config_path="configs", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    from omnidl.apps.html_report import write_report
    from omnidl.engine import evaluate
    summary = evaluate(cfg)
    print(f"report: {write_report(summary['output_dir'])}")


if __name__ == "__main__":
    main()
