"""Evaluate a checkpoint: ``python evaluate.py model=fredsnet checkpoint=PATH [data=folder data.root=DIR]``
(see docs/engine.md)."""
import hydra
from omegaconf import DictConfig

from omnidl.engine.config import register_configs

register_configs()


@hydra.main(version_base="1.3", config_path="configs", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    from omnidl.engine import evaluate
    evaluate(cfg)


if __name__ == "__main__":
    main()
