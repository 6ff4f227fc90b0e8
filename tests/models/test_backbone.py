"""omnidl.models._backbone: a residual block in training runs its own forward with each convolution through
:func:`omnidl.nn.unfold_conv.module_conv2d`; outputs, every gradient and the batch-norm statistics must be the
block's own (1e-5 of their scale, float32), on maps small enough for the weight-heavy product to take over."""
from __future__ import annotations

import copy

import pytest
import torch
import torch.nn as nn
from torchvision.models.resnet import BasicBlock, Bottleneck

import omnidl.nn.unfold_conv as U
from omnidl.models._backbone import residual_block


def _close(a, b, tol=1e-5):
    scale = b.abs().max().clamp_min(1e-30)
    torch.testing.assert_close(a / scale, b / scale, rtol=0, atol=tol)


def _downsample(cin, cout, stride):
    return nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride, bias=False), nn.BatchNorm2d(cout))


# (name, block factory, input shape, the convolutions that take the product)
BLOCKS = [
    ("bottleneck, identity", lambda: Bottleneck(256, 64), (1, 256, 2, 4), 3),
    ("bottleneck, strided downsampling", lambda: Bottleneck(128, 64, 2, _downsample(128, 256, 2)), (1, 128, 4, 8), 4),
    ("basic block, downsampling", lambda: BasicBlock(32, 64, 1, _downsample(32, 64, 1)), (2, 32, 2, 2), 3),
    ("batch 2, too large to be weight-heavy: the 1x1s pointwise", lambda: Bottleneck(64, 16), (2, 64, 8, 8), 2),
    ("maps too large for any product", lambda: Bottleneck(256, 64), (1, 256, 48, 48), 0),
]


@pytest.mark.parametrize("name,make,shape,products", BLOCKS, ids=[b[0] for b in BLOCKS])
def test_training_block_equals_the_block_itself(name, make, shape, products, monkeypatch):
    torch.manual_seed(0)
    ours = make().train()
    ref = copy.deepcopy(ours)
    x = torch.randn(shape)
    xo, xr = x.clone().requires_grad_(), x.clone().requires_grad_()
    taken = []
    real = U.unfold_conv2d
    monkeypatch.setattr(U, "unfold_conv2d", lambda *a, **k: taken.append(1) or real(*a, **k))
    y = residual_block(ours, xo)
    assert len(taken) == products
    y_ref = ref(xr)
    _close(y, y_ref)
    g = torch.randn_like(y_ref)
    y.backward(g)
    y_ref.backward(g)
    _close(xo.grad, xr.grad)
    for (n, p), (_, q) in zip(ours.named_parameters(), ref.named_parameters()):
        _close(p.grad, q.grad)
    for (n, b), (_, c) in zip(ours.named_buffers(), ref.named_buffers()):
        torch.testing.assert_close(b.float(), c.float(), rtol=1e-5, atol=1e-6, msg=n)


def test_a_hooked_block_is_called_as_a_module():
    block = Bottleneck(256, 64).train()
    seen = []
    block.register_forward_hook(lambda m, i, o: seen.append(o.shape))
    residual_block(block, torch.randn(1, 256, 2, 4))
    assert seen == [torch.Size([1, 256, 2, 4])]
