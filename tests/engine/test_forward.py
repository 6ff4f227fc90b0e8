"""The shared forward pass: batches to a device, autocast, outputs back in float32."""
import torch

from omnidl.engine.forward import float_outputs, forward, to_device


class _Half(torch.nn.Module):
    def forward(self, x):
        return {"depth": (x * 2).to(torch.float16), "label": x.argmax(1), "note": "kept"}


def test_to_device_moves_tensors_only(device, dtype):
    batch = {"image": torch.rand(2, 3, 4, 8, dtype=dtype), "meta": [{"name": "a"}, {"name": "b"}], "n": 2}
    moved = to_device(batch, device)
    assert moved["image"].device.type == device.type and moved["image"].dtype == dtype
    assert moved["meta"] is batch["meta"] and moved["n"] == 2


def test_forward_returns_float32_outputs(device, dtype):
    batch = to_device({"image": torch.rand(2, 3, 4, 8, dtype=dtype)}, device)
    for amp in (False, True):
        out = forward(_Half(), batch, device, amp)
        assert out["depth"].dtype == torch.float32 and out["label"].dtype == torch.int64 and out["note"] == "kept"
        assert torch.allclose(out["depth"], (batch["image"] * 2).float(), atol=1e-2)
    assert float_outputs({"x": torch.ones(1, dtype=torch.float64)})["x"].dtype == torch.float32
