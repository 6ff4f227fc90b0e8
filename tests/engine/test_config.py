import pytest
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ConfigKeyError, ValidationError

from .engine_helpers import make_cfg


@pytest.mark.parametrize("override", ["trainer.max_stpes=3", "optim.lrr=1", "sched.warmup=3", "eval.rotation=[1]"])
def test_typos_fail_loudly(tmp_path, override):
    name = "evaluate" if override.startswith("eval.") else "train"
    with pytest.raises((ConfigCompositionException, ConfigKeyError)):
        make_cfg(tmp_path, [override], config_name=name)


@pytest.mark.parametrize("override", ["optim.lr=fast", "trainer.max_steps=many", "trainer.amp=maybe"])
def test_wrong_types_fail(tmp_path, override):
    with pytest.raises((ConfigCompositionException, ValidationError)):
        make_cfg(tmp_path, [override])


def test_groups_compose_and_defaults(tmp_path):
    cfg = make_cfg(tmp_path, ["optim=sgd", "sched=none", "trainer=debug"], standin=False)
    assert cfg.optim.name == "sgd" and cfg.optim.momentum == 0.9 and cfg.sched.name == "none"
    assert cfg.trainer.max_steps == 4 and cfg.paths.output_dir == str(tmp_path)
    assert cfg.postprocess == [] and cfg.model is None and cfg.viz._target_.endswith("PanoramaVisualizer")
    ev = make_cfg(tmp_path, ["eval.rotation_deg=[0,5,10]", "data=folder", "data.root=/x"], config_name="evaluate",
                  standin=False)
    assert list(ev.eval.rotation_deg) == [0, 5, 10] and ev.data.test.root == "/x"
    assert ev.data.test._target_ == "omnidl.data.folder.ImageFolder"


def test_every_data_config_composes(tmp_path):
    for name in ("stanford2d3ds", "matterport3d", "folder"):
        cfg = make_cfg(tmp_path, [f"data={name}", "data.root=/r"], standin=False)
        for split in ("train", "val", "test"):
            node = cfg.data.get(split)
            if node is not None:
                assert node.root == "/r"


def test_run_dirs_are_unique_per_command(tmp_path):
    """Two commands started in the same second get different Hydra run dirs (ms + process id in the name)."""
    from hydra import compose, initialize_config_dir

    from omnidl.engine.config import register_configs, run_stamp

    from .engine_helpers import ROOT
    register_configs()
    for name in ("train", "evaluate"):
        with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "configs"), job_name="t"):
            cfg = compose(config_name=name, return_hydra_config=True)
        assert "${run_stamp:" in cfg.hydra.run._get_node("dir")._value(), name
    assert str(__import__("os").getpid()) in run_stamp()


def test_the_default_trainer_validates_and_checkpoints_by_wall_time(tmp_path):
    cfg = make_cfg(tmp_path, [], standin=False)
    assert cfg.trainer.val_every_minutes > 0 and cfg.trainer.ckpt_every_minutes > 0
    assert cfg.trainer.save_optimizer is False and cfg.trainer.resume_override is False
