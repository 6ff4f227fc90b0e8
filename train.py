"""Train a model: ``python train.py model=fredsnet [key=value ...]`` (see docs/engine.md).

Under ``torchrun --nproc_per_node=N train.py ...`` every rank shares one Hydra run dir.
"""
import sys

import hydra
from omegaconf import DictConfig

from omnidl.engine.config import register_configs
from omnidl.engine.launch import prepare_argv

register_configs()
prepare_argv()


@hydra.main(version_base="1.3", config_path="configs", config_name="train")
def main(cfg: DictConfig) -> float | None:
    if cfg.get("search"):  # python train.py +search=<name>: an Ax loss-weight search of short training runs
        from omnidl.search import run_search_from_config
        return run_search_from_config(cfg).best_objective
    from omnidl.engine import train
    from omnidl.engine.interrupt import TrainingInterrupted
    try:
        summary = train(cfg)
    except TrainingInterrupted as e:  # Ctrl-C / SIGTERM: last.pt written, the resume command logged
        sys.exit(e.exit_code)
    return summary.get("best")  # the optimised value, for Hydra sweepers


if __name__ == "__main__":
    main()
