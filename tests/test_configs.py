"""Every file in ``configs/`` (``omnidl/configs``, shipped in the package) composes (through ``train.yaml``, and
``evaluate.yaml`` for models and experiments), resolves, holds only finite numbers, and the light nodes
(cameras, losses, metrics) instantiate. YAML is read with safe loaders only (a ``!!python`` tag is refused).

The ``*-B*`` FreDSNet ablations train with the loss weights a Bayesian search writes into
``configs/loss/<search>_best.yaml``; on a fresh checkout that file does not exist and they fall back to the
thesis' hand-set weights (``loss_search`` in the experiment files), with a warning from the engine.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from omnidl.engine.build import build_metrics
from omnidl.engine.config import check_finite_config, config_root, missing_search_result, register_configs

#: the package's config tree (importlib.resources); the checkout's ``configs/`` links to it
CONFIGS = config_root()
#: groups chosen with ``group=option``; ``search`` is added with ``+search=option``
GROUPS = ("camera", "data", "loss", "metrics", "model", "optim", "sched", "trainer", "viz", "experiment")
#: folders of configs/ that are not Hydra groups of train.yaml (read by their own programs)
NOT_GROUPS = ("fisheye",)
THESIS_ALPHAS = {"alpha_semantic": 8.0, "alpha_depth": 12.0, "alpha_margin": 0.001, "alpha_object": 4.0}


def _options(group: str, root: Path = CONFIGS) -> list[str]:
    return sorted(p.stem for p in (root / group).glob("*.yaml") if not p.stem.endswith("_best"))


def _compose(overrides: list[str], config_name: str = "train", root: Path = CONFIGS):
    register_configs()
    with initialize_config_dir(version_base="1.3", config_dir=str(root), job_name="test_configs"):
        cfg = compose(config_name=config_name, overrides=["paths.output_dir=/tmp/omnidl-test-configs", *overrides])
    for key in _missing(OmegaConf.to_container(cfg, resolve=False)):  # values the user gives (data.root=???)
        OmegaConf.update(cfg, key, f"<{key}>")
    OmegaConf.to_container(cfg, resolve=True)  # every interpolation resolves
    check_finite_config(cfg, f"{config_name} {overrides}")  # no shipped config holds a nan/inf
    return cfg


def _missing(node, prefix: str = "") -> list[str]:
    """Dotted keys of the ``???`` (mandatory) values of a plain nested dict."""
    if isinstance(node, dict):
        return [k for key, v in node.items() for k in _missing(v, f"{prefix}{key}.")]
    return [prefix[:-1]] if node == "???" else []


CASES = [(g, o) for g in GROUPS for o in _options(g)] + [("+search", o) for o in _options("search")]


def test_every_config_file_is_covered():
    covered = {CONFIGS / ("search" if g == "+search" else g) / f"{o}.yaml" for g, o in CASES}
    entry = {CONFIGS / "train.yaml", CONFIGS / "evaluate.yaml"}
    others = {p for d in NOT_GROUPS for p in (CONFIGS / d).glob("*.yaml")}
    files = {p for p in CONFIGS.rglob("*.yaml") if not p.stem.endswith("_best")}
    assert files == covered | entry | others, f"configs not composed by this test: {sorted(files - covered)}"
    for path in others:
        assert isinstance(OmegaConf.to_container(OmegaConf.load(path)), dict)


@pytest.mark.parametrize("group,option", CASES, ids=[f"{g.lstrip('+')}={o}" for g, o in CASES])
def test_composes_through_train_yaml(group, option):
    cfg = _compose([f"{group}={option}"])
    node = cfg.get(group.lstrip("+")) if group not in ("experiment", "+search") else cfg
    assert node is not None
    if group in ("camera", "model") and cfg.get("camera") is not None:
        cam = instantiate(cfg.camera)
        assert cam.width > 0 and cam.height > 0
    if group in ("loss", "experiment", "model") and cfg.get("loss") is not None:
        assert callable(instantiate(cfg.loss, _convert_="all"))
    if group in ("metrics", "experiment", "model") and cfg.get("metrics") is not None:
        metrics = build_metrics(cfg)
        assert hasattr(metrics, "update") and hasattr(metrics, "compute")


@pytest.mark.parametrize("group,option", [c for c in CASES if c[0] in ("model", "experiment")],
                         ids=[f"{g}={o}" for g, o in CASES if g in ("model", "experiment")])
def test_composes_through_evaluate_yaml(group, option):
    cfg = _compose([f"{group}={option}"], config_name="evaluate")
    assert cfg.task == "evaluate" and cfg.eval.split


SEARCHED = [o for o in _options("experiment") if "-B" in o]


def test_there_are_searched_weight_experiments():
    assert len(SEARCHED) == 16


@pytest.mark.parametrize("name", SEARCHED)
def test_searched_weight_experiment_falls_back_to_the_thesis_weights(name):
    cfg = _compose([f"experiment={name}"])
    assert {k: cfg.loss[k] for k in THESIS_ALPHAS} == THESIS_ALPHAS
    assert (cfg.loss.semantic_loss == "recall") == ("-RL-" in name)
    note = missing_search_result(cfg)
    assert note and cfg.loss_search.name in note and "were not found" in note


def test_searched_weight_experiment_uses_the_search_result(tmp_path):
    root = tmp_path / "configs"
    shutil.copytree(CONFIGS, root, ignore=shutil.ignore_patterns("*_best.yaml"))
    best = OmegaConf.load(CONFIGS / "loss" / "fredsnet.yaml")
    best.alpha_depth, best.alpha_margin = 3.5, 0.02
    (root / "loss" / "fredsnet_loss_weights_best.yaml").write_text(OmegaConf.to_yaml(best))
    cfg = _compose(["experiment=F-Std-CE-B"], root=root)
    assert cfg.loss.alpha_depth == 3.5 and cfg.loss.alpha_margin == 0.02 and cfg.loss.alpha_semantic == 8.0
    assert missing_search_result(cfg) is None
    recall = _compose(["experiment=F-Std-RL-B"], root=root)  # the recall search has not run: fallback
    assert recall.loss.alpha_depth == 12.0 and missing_search_result(recall)


def test_the_checkout_configs_folder_is_the_package_tree():
    link = Path(__file__).resolve().parents[1] / "configs"
    assert link.resolve() == CONFIGS.resolve() and CONFIGS.parent.name == "omnidl"
    assert not [p for p in CONFIGS.rglob("*") if p.is_file() and p.suffix != ".yaml" and "__pycache__" not in p.parts]


def test_a_python_tag_in_a_config_is_refused(tmp_path):
    """Hydra/OmegaConf read YAML with a SafeLoader: a config that would run code on load is an error."""
    root = tmp_path / "configs"
    shutil.copytree(CONFIGS, root, ignore=shutil.ignore_patterns("*_best.yaml"))
    marker = tmp_path / "ran"
    (root / "optim" / "evil.yaml").write_text(
        f"defaults: [schema, _self_]\nname: !!python/object/apply:os.system ['touch {marker}']\n")
    with pytest.raises(Exception, match=r"python/object|constructor|could not determine"):
        _compose(["optim=evil"], root=root)
    assert not marker.exists()


_UNSAFE = {"unsafe_load", "full_load", "load_all", "unsafe_load_all", "full_load_all", "UnsafeLoader", "FullLoader",
           "Loader"}


def test_the_package_reads_yaml_with_safe_loaders_only():
    """No ``yaml.load``/``unsafe_load``/``full_load`` and no ``Loader=yaml.Loader`` anywhere in ``omnidl/``
    (``yaml.safe_load``, OmegaConf and Hydra are the readers; issue 48 item 6)."""
    import ast
    bad = []
    for path in sorted(CONFIGS.parent.rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        if "yaml" not in text:
            continue
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "yaml" \
                    and (node.attr in _UNSAFE or node.attr == "load"):
                bad.append(f"{path.relative_to(CONFIGS.parents[1])}:{node.lineno} yaml.{node.attr}")
    assert not bad, "YAML read with a loader that can construct Python objects:\n" + "\n".join(bad)
