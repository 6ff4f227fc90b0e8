"""``python tests/engine/train_driver.py [overrides]``: train.py with the stand-ins of engine_helpers.STANDIN
(a real ``@hydra.main`` process, for the kill/signal tests). ``OMNIDL_TEST_KILL_AFTER_WRITES=n``: SIGKILL this
process right after its n-th checkpoint file write (to land a kill between the best.pt and last.pt writes)."""
import os
import signal
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf, open_dict  # noqa: E402

from omnidl.engine.config import register_configs  # noqa: E402

register_configs()


def _kill_after_writes(n: int) -> None:
    import omnidl.engine.state as state
    real, count = state.save_checkpoint, [0]

    def save(path, ck):
        out = real(path, ck)
        count[0] += 1
        if count[0] == n:
            os.kill(os.getpid(), signal.SIGKILL)
        return out
    state.save_checkpoint = save


@hydra.main(version_base="1.3", config_path=str(HERE.parents[1] / "configs"), config_name="train")
def main(cfg: DictConfig) -> None:
    from engine_helpers import STANDIN

    from omnidl.engine import train
    from omnidl.engine.interrupt import TrainingInterrupted
    with open_dict(cfg):
        for k, v in STANDIN.items():
            if cfg.get(k) is None:
                cfg[k] = OmegaConf.create(v)
        cfg.loss.sleep = float(os.environ.get("OMNIDL_TEST_STEP_SLEEP", "0"))
    if os.environ.get("OMNIDL_TEST_KILL_AFTER_WRITES"):
        _kill_after_writes(int(os.environ["OMNIDL_TEST_KILL_AFTER_WRITES"]))
    try:
        train(cfg)
    except TrainingInterrupted as e:
        sys.exit(e.exit_code)


if __name__ == "__main__":
    main()
