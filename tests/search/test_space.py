import pytest
from omegaconf import OmegaConf

from omnidl.search.space import SearchConfigError, parse_search_spec

BASE = {"name": "s", "objective": {"metrics": "val"},
        "parameters": {"loss.w": {"bounds": [0.1, 10], "log": True}}}


def test_empty_range_names_key():
    cfg = {**BASE, "parameters": {"loss.w": {"bounds": [1.0, 1.0]}}}
    with pytest.raises(SearchConfigError, match=r"loss\.w"):
        parse_search_spec(cfg)


def test_log_needs_positive_bound():
    cfg = {**BASE, "parameters": {"loss.w": {"bounds": [0.0, 1.0], "log": True}}}
    with pytest.raises(SearchConfigError, match="positive"):
        parse_search_spec(cfg)


def test_unknown_parameter_fails_against_training_config():
    train = OmegaConf.create({"loss": {"w": 1.0, "v": 2.0}})
    parse_search_spec(BASE, train)
    cfg = {**BASE, "parameters": {"loss.w_typo": {"bounds": [0.1, 1.0]}}}
    with pytest.raises(SearchConfigError, match=r"loss\.w_typo"):
        parse_search_spec(cfg, train)


def test_unknown_search_field():
    with pytest.raises(SearchConfigError, match="trails"):
        parse_search_spec({**BASE, "trails": 3})


def test_scalarisation():
    spec = parse_search_spec({**BASE, "objective": {"metrics": {"a": 1.0, "b": -2.0}}})
    assert spec.scalarise({"a": 3.0, "b": 1.0}) == pytest.approx(1.0)
    with pytest.raises(KeyError):
        spec.scalarise({"a": 1.0})
