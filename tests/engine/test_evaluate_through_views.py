"""evaluate.py's ``data.through_views`` (omnidl.engine.evaluator._through_views): the data config, not the model,
decides that a perspective network trained on views is evaluated on whole images through the view chain. The
weights stay in the plain model (wrapped after loading); other splits and other data configs keep the model as it
is; a bad option or a missing camera names the field."""
from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from omnidl.engine.evaluator import _through_views
from omnidl.geometry.views import ThroughViews

VIEWS = {"layout": "cube", "size": 16, "fov": None, "align": "scale", "assumed_range": 3.0}
CAMERA = {"_target_": "omnidl.cameras.build", "type": "equirect", "width": 64, "height": 32}


class _Net(torch.nn.Module):
    def forward(self, x):
        return {"depth": torch.ones_like(x[:, :1])}


def _cfg(through_views=VIEWS, split="test", camera=CAMERA):
    return OmegaConf.create({"data": {"through_views": through_views}, "eval": {"split": split}, "camera": camera})


def test_the_data_config_wraps_the_loaded_model_for_its_split(caplog):
    net = _Net()
    with caplog.at_level("INFO", logger="omnidl.engine"):
        wrapped = _through_views(_cfg(), net)
    assert isinstance(wrapped, ThroughViews) and wrapped.net is net and not wrapped.training
    assert (wrapped.layout, wrapped.size, len(wrapped.views)) == ("cube", 16, 6)
    assert (wrapped.camera.width, wrapped.camera.height) == (64, 32)
    assert "through the view chain" in caplog.text
    assert wrapped(torch.rand(1, 3, 32, 64))["depth"].shape == (1, 1, 32, 64)
    assert _through_views(OmegaConf.create({"data": {"test": {}}, "eval": {"split": "test"}}), net) is net
    assert _through_views(_cfg(through_views=None), net) is net
    assert _through_views(_cfg(split="val"), net) is net                          # the views themselves
    assert isinstance(_through_views(_cfg({**VIEWS, "split": "val"}, split="val"), net), ThroughViews)


def test_bad_options_name_the_field():
    with pytest.raises(ValueError, match=r"data.through_views: .*unknown key\(s\) \['sizes'\]"):
        _through_views(_cfg({**VIEWS, "sizes": 16}), _Net())
    with pytest.raises(ValueError, match="camera="):
        _through_views(_cfg(camera=None), _Net())
