"""Training and evaluation engine: ``train(cfg) -> dict`` and ``evaluate(cfg) -> dict`` on Hydra configs."""
from .config import register_configs
from .trainer import train


def evaluate(cfg):
    """Evaluate a checkpoint (see :func:`omnidl.engine.evaluator.evaluate`)."""
    from .evaluator import evaluate as _evaluate
    return _evaluate(cfg)


__all__ = ["train", "evaluate", "register_configs"]
