"""``omnidl predict --compile``: the network compiled with torch.compile (Inductor, freezing) gives the same
outputs as the plain one, up to float rounding; the compile time is printed; the weights really are frozen
(constants of the compiled graph)."""
from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_predict_helpers import tiny_checkpoint  # noqa: E402

from omnidl.apps.cli import main as omnidl_main  # noqa: E402
from omnidl.apps.predict.loader import load_predictor  # noqa: E402
from omnidl.engine.compile import FrozenInference, inductor_problem  # noqa: E402

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(inductor_problem("cpu") is not None, reason="torch.compile/Inductor unavailable")]


@pytest.fixture(scope="module")
def unet_ckpt(tmp_path_factory):
    return tiny_checkpoint(tmp_path_factory.mktemp("compile") / "unet.pt", "unet")


def test_compiled_predictor_equals_the_plain_one(unet_ckpt):
    plain = load_predictor(unet_ckpt)
    comp = load_predictor(unet_ckpt, compile=True)
    assert isinstance(comp.model, FrozenInference) and comp.info["compiled"]
    assert comp.info["compile_s"] >= 0 and comp.info["first_call_s"] >= comp.info["call_s"] >= 0
    assert comp.outputs == plain.outputs == {"depth", "semantic"}
    assert list(comp.model.compiled._orig_mod.state_dict()) == list(plain.model.state_dict())
    torch.manual_seed(0)
    for image in (torch.rand(3, 32, 64), torch.rand(3, 50, 100)):       # the network size and a resized one
        a, b = plain(image), comp(image)
        assert a.keys() == b.keys()
        for k in a:
            torch.testing.assert_close(b[k], a[k], rtol=1e-4, atol=1e-5)
    # freezing: the weights are constants of the compiled graph (folded, prepacked copies), not graph inputs, so
    # the compiled model does not follow an edit of them as the plain one does (without freezing it would)
    x = torch.rand(3, 32, 64)
    with torch.no_grad():
        for module in (plain.model, comp.model):
            for p in module.parameters():
                p.mul_(2)
    edited = plain(x)["depth"]
    assert not torch.allclose(comp(x)["depth"], edited, rtol=1e-3, atol=1e-3)


def test_predict_depth_compile_writes_the_same_depth(unet_ckpt, tmp_path, capsys):
    img = tmp_path / "pano.png"
    rng = np.random.default_rng(0)
    cv2.imwrite(str(img), rng.integers(0, 255, (48, 96, 3), dtype=np.uint8))
    common = ["predict", "depth", str(img), "--checkpoint", str(unet_ckpt), "--upright", "off", "--no-ply"]
    assert omnidl_main([*common, "--out", str(tmp_path / "plain")]) == 0
    assert "compiled the model" not in capsys.readouterr().out
    assert omnidl_main([*common, "--out", str(tmp_path / "compiled"), "--compile"]) == 0
    out = capsys.readouterr().out
    assert "compiled the model in " in out and "Inductor with freezing" in out
    a = np.load(tmp_path / "plain" / "pano_depth.npy")
    b = np.load(tmp_path / "compiled" / "pano_depth.npy")
    assert a.shape == (48, 96) and np.allclose(a, b, rtol=1e-4, atol=1e-5)
    sa = cv2.imread(str(tmp_path / "plain" / "pano_semantic.png"), cv2.IMREAD_UNCHANGED)
    sb = cv2.imread(str(tmp_path / "compiled" / "pano_semantic.png"), cv2.IMREAD_UNCHANGED)
    assert (sa != sb).mean() < 0.01            # argmax of logits equal up to rounding: ties may flip a pixel


def test_compile_refused_where_inductor_is_missing(unet_ckpt, tmp_path, capsys, monkeypatch):
    import omnidl.engine.compile as comp
    monkeypatch.setattr(comp, "inductor_problem", lambda device: "no C++ compiler found")
    img = tmp_path / "pano.png"
    cv2.imwrite(str(img), np.zeros((16, 32, 3), np.uint8))
    assert omnidl_main(["predict", "depth", str(img), "--checkpoint", str(unet_ckpt), "--out", str(tmp_path / "o"),
                        "--compile"]) == 2
    err = capsys.readouterr().err
    assert "--compile: torch.compile with Inductor is not available" in err and "no C++ compiler found" in err
    assert "Leave out --compile" in err
