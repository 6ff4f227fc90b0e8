"""The engine's config schemas, where the config tree lives (inside the package), and the refusal of
non-finite values where a config is read (check_finite_config)."""
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ConfigKeyError, ValidationError

from omnidl.engine.config import check_finite_config

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


# ------------------------------------------------------------------ where the configs are (issue 49 item 2)

def test_the_config_tree_is_inside_the_package():
    """omnidl/configs, found with importlib.resources (a wheel install has it); the checkout's configs/ is it."""
    import omnidl
    from omnidl.engine.config import config_root

    from .engine_helpers import ROOT
    root = config_root()
    assert root == __import__("pathlib").Path(omnidl.__file__).parent / "configs"
    assert (root / "train.yaml").is_file() and (root / "evaluate.yaml").is_file() and (root / "camera").is_dir()
    assert (ROOT / "configs").resolve() == root.resolve()


def test_the_entry_points_compose_from_the_package_tree(tmp_path):
    """train.py/evaluate.py (thin wrappers) and ``omnidl train|evaluate`` share one Hydra app per task, whose
    primary config folder is the package's and whose job name stays train/evaluate (train.log, outputs/...)."""
    import train as train_script  # noqa: F401 (the checkout's wrapper imports cleanly)

    from omnidl.apps import evaluate as ev_app
    from omnidl.apps import train as train_app
    from omnidl.engine.config import config_root
    for app, name in ((train_app, "train"), (ev_app, "evaluate")):
        assert app._run.__module__ == f"omnidl.apps.{name}"
        closure = {c.cell_contents for c in (app._run.__closure__ or ()) if isinstance(c.cell_contents, str)}
        assert str(config_root()) in closure and name in closure, closure


# ------------------------------------------------------------------ non-finite values (issue 48 item 4)

NON_FINITE = [float("nan"), float("inf"), float("-inf")]


@pytest.mark.parametrize("override,key", [("loss.alpha_depth=nan", "loss.alpha_depth"),
                                          ("optim.lr=inf", "optim.lr"),
                                          ("trainer.grad_clip=-inf", "trainer.grad_clip"),
                                          ("++data.depth_max=nan", "data.depth_max"),
                                          ("optim.betas=[0.9,nan]", "optim.betas[1]")])
def test_non_finite_config_values_are_refused_naming_the_key(tmp_path, override, key):
    cfg = make_cfg(tmp_path, ["model=fredsnet", override], standin=False)
    with pytest.raises(ValueError, match=r"non-finite") as e:
        check_finite_config(cfg)
    assert f"{key}=" in str(e.value), str(e.value)


def test_every_shipped_config_is_finite(tmp_path):
    for overrides in (["model=fredsnet"], ["model=horizonnet_nc"], ["experiment=F-Std-CE-B"]):
        check_finite_config(make_cfg(tmp_path, overrides, standin=False))
    check_finite_config(make_cfg(tmp_path, ["model=fredsnet"], config_name="evaluate", standin=False))


def test_interpolations_count_with_their_value_and_unresolvable_ones_are_skipped():
    from omegaconf import OmegaConf
    cfg = OmegaConf.create({"a": float("nan"), "b": "${a}", "c": "???", "d": "${hydra:runtime.output_dir}",
                            "e": "nan", "f": [1, {"g": 2.5}]})
    with pytest.raises(ValueError) as e:
        check_finite_config(cfg)
    assert "a=nan" in str(e.value) and "b=nan" in str(e.value) and "e=" not in str(e.value)
    check_finite_config({"x": 1.0, "y": [1, 2, {"z": -3e300}], "s": "inf", "n": None, "t": True})


_KEYS = st.sampled_from(["a", "lr", "alpha", "w"])
_leaf = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(), st.booleans(), st.none(),
                  st.text(alphabet="xyz", max_size=3))
_tree = st.recursive(_leaf, lambda kids: st.one_of(st.lists(kids, max_size=3), st.dictionaries(_KEYS, kids, max_size=3)),
                     max_leaves=10)


def _non_finite_keys(node, prefix=""):
    """Dotted keys (``a.b[1].c``) of the non-finite float leaves of a plain nested dict/list."""
    if isinstance(node, dict):
        return [k for key, v in node.items() for k in _non_finite_keys(v, f"{prefix}{key}.")]
    if isinstance(node, list):
        return [k for i, v in enumerate(node) for k in _non_finite_keys(v, f"{prefix[:-1]}[{i}].")]
    return [prefix[:-1]] if isinstance(node, float) and not math.isfinite(node) else []


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.dictionaries(_KEYS, _tree, min_size=1, max_size=4))
def test_property_a_config_is_refused_iff_it_holds_a_non_finite_number(tree):
    """Generated nested configs: refused exactly when some float leaf is nan/inf, and the error names every such
    key; finite configs pass unchanged."""
    bad = _non_finite_keys(tree)
    if not bad:
        check_finite_config(tree)
        return
    with pytest.raises(ValueError) as e:
        check_finite_config(tree)
    for key in bad:
        assert f"{key}=" in str(e.value), (key, str(e.value))


@pytest.mark.slow
def test_train_py_refuses_a_nan_weight_before_building_anything(tmp_path):
    """``python train.py model=fredsnet loss.alpha_depth=nan`` stops at once with the key and value named (today's
    main trains without the depth loss); nothing is written."""
    import os
    import subprocess
    import sys

    from .engine_helpers import ROOT
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    smoke = ["trainer=debug", "trainer.max_steps=1", "trainer.val_max_batches=1", "trainer.batch_size=1",
             "++data.train_length=1", "++data.val_length=1", "trainer.tensorboard=false", "trainer.progress=false",
             "data.width=64", "data.height=32"]  # (a main without the check trains one tiny step)
    r = subprocess.run([sys.executable, str(ROOT / "train.py"), "model=fredsnet", "loss.alpha_depth=nan", *smoke,
                        f"hydra.run.dir={tmp_path / 'run'}", "hydra.output_subdir=null"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120, env=dict(env, OMP_NUM_THREADS="1"))
    assert r.returncode == 2, r.stdout[-2000:] + r.stderr[-2000:]
    assert "loss.alpha_depth=nan" in r.stderr and "non-finite" in r.stderr
    assert not (tmp_path / "run" / "checkpoints").exists()
