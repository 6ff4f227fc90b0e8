"""Every registered model exports with ``torch.export`` in each of its convolution modes (the model contract,
tests/models/test_all_models.py) and, where onnx/onnxruntime are installed (the ``export`` and ``dev`` extras), to
ONNX with onnxruntime outputs within 1e-4 of eager PyTorch.

The models run in their small registry configuration (``smoke_config``) on CPU. A projected convolution exports as
calls of the registered ops ``omnidl::projected_sampling`` and ``omnidl::fixed_offset_conv2d``; ONNX has no such
operator, so the ONNX parity runs the standard convolutions. All four models export to ONNX (opset 18 via the
dynamo exporter), FreDSNet's FFT included (ONNX ``DFT``)."""
from __future__ import annotations

import pytest
import torch

from omnidl.models import create_model, list_models
from omnidl.models.registry import smoke_config

from .test_all_models import IDS, VARIANTS, build

pytestmark = [
    pytest.mark.slow,
    # torch.export gives this warning for HorizonNet's nn.LSTM; it gives it for a bare nn.LSTM too (torch 2.14.1)
    pytest.mark.filterwarnings(r"ignore:The tensor attributes self\.rnn\._flat_weights"),
]

def _model(name: str, extra: dict):
    cfg = smoke_config(name)
    torch.manual_seed(0)
    model = create_model(name, **dict(cfg["kwargs"], **extra)).eval()
    x = torch.rand(1, 3, *cfg["size"], generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        ref = model(x)
    return model, x, ref


@pytest.mark.parametrize("name,conv", VARIANTS, ids=IDS)
def test_torch_export(name, conv):
    model, x = build(name, conv)
    model.eval()
    ep = torch.export.export(model, (x,))
    with torch.no_grad():
        ref = model(x)
        out = ep.module()(x)
    assert set(out) == set(ref)
    for k in ref:
        torch.testing.assert_close(out[k], ref[k], atol=1e-5, rtol=1e-5, msg=f"{name}: output {k}")


@pytest.mark.parametrize("name", list_models())
def test_onnx_parity(name, tmp_path):
    pytest.importorskip("onnx")
    pytest.importorskip("onnxscript")
    ort = pytest.importorskip("onnxruntime")
    model, x, ref = _model(name, {})
    path = tmp_path / f"{name}.onnx"
    torch.onnx.export(model, (x,), str(path), dynamo=True, output_names=list(ref), external_data=False,
                      verbose=False)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    outs = sess.run(None, {sess.get_inputs()[0].name: x.numpy()})
    names = [o.name for o in sess.get_outputs()]
    assert names == list(ref)
    for k, o in zip(names, outs):
        err = float((torch.from_numpy(o) - ref[k]).abs().max())
        assert err < 1e-4, f"{name}: ONNX output {k} differs from PyTorch by {err:.2e}"
