"""omnidl.nn.batch_norm: the native training forward against nn.BatchNorm2d's own."""
from __future__ import annotations

import copy

import pytest
import torch
import torch.nn as nn

from omnidl.nn import batch_norm, native

pytestmark = pytest.mark.skipif(native.library() is None, reason="native library not built")


def _pair(C: int, **kw) -> tuple[nn.BatchNorm2d, nn.BatchNorm2d]:
    """A plain nn.BatchNorm2d with random affine parameters and running statistics, and a converted copy."""
    ref = nn.BatchNorm2d(C, **kw)
    g = torch.Generator().manual_seed(C)
    with torch.no_grad():
        if ref.affine:
            ref.weight.uniform_(0.5, 1.5, generator=g)
            ref.bias.normal_(generator=g)
        if ref.track_running_stats:
            ref.running_mean.normal_(generator=g)
            ref.running_var.uniform_(0.5, 2.0, generator=g)
    return ref, batch_norm.convert(copy.deepcopy(ref))


def _native_calls(monkeypatch) -> list:
    """The native forwards' (B, C, hw) from now on; each native backward appends ("backward", B, C, hw)."""
    calls: list = []
    lib = native.library()
    real, real_backward = lib.omnidl_bn_train, lib.omnidl_bn_train_backward

    def counted(*args):
        calls.append(args[1:4])
        return real(*args)

    def counted_backward(*args):
        calls.append(("backward", *args[2:5]))
        return real_backward(*args)
    monkeypatch.setattr(lib, "omnidl_bn_train", counted)
    monkeypatch.setattr(lib, "omnidl_bn_train_backward", counted_backward)
    return calls


# (name, input shape (B, C, H, W), nn.BatchNorm2d keywords): each runs natively and must match nn.BatchNorm2d
CASES = [
    ("one image, planes of whole vectors", (1, 8, 16, 32), {}),
    ("a batch, ragged planes", (3, 5, 7, 9), {}),
    ("planes shorter than a vector", (2, 16, 2, 3), {}),
    ("many channels on a 4x8 map", (1, 512, 4, 8), {}),
    ("cumulative average (momentum None)", (2, 4, 5, 6), {"momentum": None}),
    ("no affine parameters", (2, 4, 5, 6), {"affine": False}),
    ("no running statistics", (2, 4, 5, 6), {"track_running_stats": False}),
    ("two values per channel", (2, 3, 1, 1), {}),
]


GRADIENT_LAYOUT = [("a channels-last gradient: PyTorch's backward", (2, 8, 5, 6), {"layout": torch.channels_last})]


@pytest.mark.parametrize("name,shape,kw", CASES + GRADIENT_LAYOUT, ids=[c[0] for c in CASES + GRADIENT_LAYOUT])
def test_training_forward_and_backward_match_pytorch(name, shape, kw, monkeypatch):
    calls = _native_calls(monkeypatch)
    kw = dict(kw)
    layout = kw.pop("layout", torch.contiguous_format)
    ref, new = _pair(shape[1], **kw)
    g = torch.Generator().manual_seed(1)
    x = (torch.randn(shape, generator=g) * 3 + 1).requires_grad_()
    x2 = x.detach().clone().requires_grad_()
    gy = torch.randn(shape, generator=g).contiguous(memory_format=layout)
    for _ in range(2):                                   # the running statistics' update twice
        y1, y2 = ref(x), new(x2)
        y1.backward(gy)
        y2.backward(gy)
    backwards = 0 if layout is torch.channels_last else 2
    assert len(calls) == 2 + backwards and type(new) is batch_norm.BatchNorm2d
    assert sum(c[0] == "backward" for c in calls) == backwards
    torch.testing.assert_close(y2, y1, rtol=0, atol=1e-5)
    assert y2.is_contiguous()
    torch.testing.assert_close(x2.grad, x.grad, rtol=1e-5, atol=1e-5)
    if ref.affine:
        torch.testing.assert_close(new.weight.grad, ref.weight.grad, rtol=1e-5, atol=1e-4)
        torch.testing.assert_close(new.bias.grad, ref.bias.grad, rtol=1e-5, atol=1e-4)
    for key, value in ref.state_dict().items():
        torch.testing.assert_close(new.state_dict()[key], value, rtol=1e-6, atol=1e-6)


def test_statistics_of_a_large_offset_are_exact():
    # float64 sums: a map of values 1e4 + N(0, 1) normalises to unit variance, as PyTorch's
    ref, new = _pair(4)
    x = 1e4 + torch.randn(2, 4, 33, 65, generator=torch.Generator().manual_seed(3))
    y = new(x)
    torch.testing.assert_close(y, ref(x), rtol=0, atol=2e-3)
    xd = x.double()
    mean, var = xd.mean((0, 2, 3)), xd.var((0, 2, 3), unbiased=False)
    want = (xd - mean[:, None, None]) / (var[:, None, None] + new.eps).sqrt()
    want = want * new.weight.double()[:, None, None] + new.bias.double()[:, None, None]
    torch.testing.assert_close(y.double(), want, rtol=0, atol=2e-4)


def test_second_derivatives_under_create_graph_are_autograds():
    ref, new = _pair(3)
    x = torch.randn(2, 3, 4, 5, dtype=torch.float32, generator=torch.Generator().manual_seed(4), requires_grad=True)
    out = []
    for m in (ref, new):
        y = m(x)
        (gx,) = torch.autograd.grad((y ** 2).sum(), x, create_graph=True)
        (ggx,) = torch.autograd.grad(gx.sum(), x)
        out.append((gx, ggx))
    torch.testing.assert_close(out[1][0], out[0][0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out[1][1], out[0][1], rtol=1e-4, atol=1e-4)


def _eval(bn, x):
    bn.eval()
    return x


# (name, how to make the case from (module, input), the error PyTorch gives or None): nn.BatchNorm2d's own forward
FALLBACKS = [
    ("eval mode", _eval, None),
    ("channels-last input", lambda bn, x: x.contiguous(memory_format=torch.channels_last), None),
    ("a channel slice (not contiguous)", lambda bn, x: torch.cat([x, x], 1)[:, ::2], None),
    ("float64", lambda bn, x: (bn.double(), x.double())[1], None),
    ("one value per channel", lambda bn, x: x[:1, :, :1, :1], ValueError),
    ("3-d input", lambda bn, x: x[0], ValueError),
    ("switched off", lambda bn, x: x, None),
]


@pytest.mark.parametrize("name,make,error", FALLBACKS, ids=[c[0] for c in FALLBACKS])
def test_other_inputs_take_pytorchs_forward(name, make, error, monkeypatch):
    calls = _native_calls(monkeypatch)
    if name == "switched off":
        monkeypatch.setattr(batch_norm, "ENABLED", False)
    ref, new = _pair(4)
    x = torch.randn(2, 4, 6, 8, generator=torch.Generator().manual_seed(5))
    xr, xn = make(ref, x.clone()), make(new, x.clone())
    if error is not None:
        with pytest.raises(error):
            new(xn)
        with pytest.raises(error):
            ref(xr)
    else:
        torch.testing.assert_close(new(xn), ref(xr), rtol=0, atol=0)
        torch.testing.assert_close(new.running_var, ref.running_var, rtol=0, atol=0)
    assert calls == []


def test_convert_keeps_subclasses_and_state_dict_keys():
    class Own(nn.BatchNorm2d):
        pass
    m = nn.Sequential(nn.Conv2d(3, 4, 1), nn.BatchNorm2d(4), Own(4), nn.Sequential(nn.BatchNorm2d(4)))
    keys = list(m.state_dict())
    batch_norm.convert(m)
    assert [type(x) for x in (m[1], m[2], m[3][0])] == [batch_norm.BatchNorm2d, Own, batch_norm.BatchNorm2d]
    assert list(m.state_dict()) == keys
    assert isinstance(m[1], nn.BatchNorm2d)


def _act_pair(kind: str, C: int) -> tuple[nn.Module, nn.Module]:
    """An activation module and a copy: ``relu``, ``prelu`` (omnidl's, one slope per channel), ``prelu1`` (one for
    all), ``nn.prelu`` (PyTorch's module) or ``identity``; the slopes random in [-0.5, 0.5]."""
    from omnidl.nn.prelu import PReLU
    make = {"relu": nn.ReLU, "prelu": lambda: PReLU(C), "prelu1": lambda: PReLU(1), "nn.prelu": lambda: nn.PReLU(C),
            "identity": nn.Identity}[kind]
    act = make()
    if hasattr(act, "weight"):
        with torch.no_grad():
            act.weight.uniform_(-0.5, 0.5, generator=torch.Generator().manual_seed(7))
    return act, copy.deepcopy(act)


# (name, input shape, nn.BatchNorm2d keywords, activation of _act_pair, gradient layout): act(bn(x)) in the native
# passes of one batch norm, against the two modules in PyTorch
ACT_CASES = [
    ("relu", (2, 8, 16, 32), {}, "relu", torch.contiguous_format),
    ("prelu per channel", (2, 8, 16, 32), {}, "prelu", torch.contiguous_format),
    ("prelu, one slope", (3, 5, 7, 9), {}, "prelu1", torch.contiguous_format),
    ("nn.PReLU", (1, 16, 2, 3), {}, "nn.prelu", torch.contiguous_format),
    ("identity", (1, 512, 4, 8), {}, "identity", torch.contiguous_format),
    ("relu, no affine, cumulative average", (2, 4, 5, 6), {"affine": False, "momentum": None}, "relu",
     torch.contiguous_format),
    ("prelu, no running statistics", (2, 4, 5, 6), {"track_running_stats": False}, "prelu", torch.contiguous_format),
    ("prelu, a channels-last gradient (made contiguous)", (2, 8, 5, 6), {}, "prelu", torch.channels_last),
]


@pytest.mark.parametrize("name,shape,kw,kind,layout", ACT_CASES, ids=[c[0] for c in ACT_CASES])
def test_batch_norm_with_activation_matches_the_two_modules(name, shape, kw, kind, layout, monkeypatch):
    calls = _native_calls(monkeypatch)
    ref, new = _pair(shape[1], **kw)
    act_ref, act = _act_pair(kind, shape[1])
    g = torch.Generator().manual_seed(1)
    x = (torch.randn(shape, generator=g) * 3 + 1).requires_grad_()
    x2 = x.detach().clone().requires_grad_()
    gy = torch.randn(shape, generator=g).contiguous(memory_format=layout)
    for _ in range(2):                                   # the running statistics' update twice
        y1, y2 = act_ref(ref(x)), batch_norm.with_activation(x2, new, act)
        y1.backward(gy)
        y2.backward(gy)
    assert len(calls) == 4 and sum(c[0] == "backward" for c in calls) == 2
    torch.testing.assert_close(y2, y1, rtol=0, atol=1e-5)
    assert y2.is_contiguous()
    torch.testing.assert_close(x2.grad, x.grad, rtol=1e-5, atol=1e-5)
    for p_new, p_ref in zip([*new.parameters(), *act.parameters()], [*ref.parameters(), *act_ref.parameters()]):
        torch.testing.assert_close(p_new.grad, p_ref.grad, rtol=1e-5, atol=1e-4)
    for key, value in ref.state_dict().items():
        torch.testing.assert_close(new.state_dict()[key], value, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("kind", ["relu", "prelu"])
def test_batch_norm_with_activation_keeps_pytorchs_sides_of_nan(kind):
    # a NaN in a channel makes its statistics NaN: every value of that channel, and its gradients, as in PyTorch
    ref, new = _pair(3)
    act_ref, act = _act_pair(kind, 3)
    x = torch.randn(2, 3, 4, 5, generator=torch.Generator().manual_seed(2))
    x[1, 1, 2, 3] = float("nan")
    x, x2 = x.requires_grad_(), x.detach().clone().requires_grad_()
    y1, y2 = act_ref(ref(x)), batch_norm.with_activation(x2, new, act)
    gy = torch.randn(x.shape, generator=torch.Generator().manual_seed(3))
    y1.backward(gy)
    y2.backward(gy)
    torch.testing.assert_close(y2, y1, rtol=0, atol=1e-5, equal_nan=True)
    torch.testing.assert_close(x2.grad, x.grad, rtol=1e-5, atol=1e-5, equal_nan=True)


def test_batch_norm_with_activation_second_derivatives_are_autograds():
    ref, new = _pair(3)
    act_ref, act = _act_pair("prelu", 3)
    x = torch.randn(2, 3, 4, 5, generator=torch.Generator().manual_seed(4), requires_grad=True)
    out = []
    for y in (act_ref(ref(x)), batch_norm.with_activation(x, new, act)):
        gx, gs = torch.autograd.grad((y ** 2).sum(), [x, act.weight if len(out) else act_ref.weight],
                                     create_graph=True)
        out.append((gx, gs, torch.autograd.grad(gx.sum() + gs.sum(), x)[0]))
    for a, b in zip(out[1], out[0]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)


def _hooked(module: nn.Module) -> nn.Module:
    module.register_forward_hook(lambda *args: None)
    return module


# (name, how to make (norm, act, x) from a converted norm, an omnidl PReLU and an input): with_activation declines
# (returns None) and the caller runs the modules
DECLINED = [
    ("a plain nn.BatchNorm2d", lambda bn, act, x: (nn.BatchNorm2d(4), act, x)),
    ("eval mode", lambda bn, act, x: (bn.eval(), act, x)),
    ("channels-last input", lambda bn, act, x: (bn, act, x.contiguous(memory_format=torch.channels_last))),
    ("another activation", lambda bn, act, x: (bn, nn.GELU(), x)),
    ("a hook on the norm", lambda bn, act, x: (_hooked(bn), act, x)),
    ("a hook on the activation", lambda bn, act, x: (bn, _hooked(act), x)),
    ("a float64 slope", lambda bn, act, x: (bn, act.double(), x)),
    ("three slopes for four channels", lambda bn, act, x: (bn, nn.PReLU(3), x)),
    ("switched off", lambda bn, act, x: (bn, act, x)),
]


@pytest.mark.parametrize("name,make", DECLINED, ids=[c[0] for c in DECLINED])
def test_batch_norm_with_activation_declines(name, make, monkeypatch):
    calls = _native_calls(monkeypatch)
    if name == "switched off":
        monkeypatch.setattr(batch_norm, "FUSE_ACTIVATION", False)
    _, bn = _pair(4)
    act, _ = _act_pair("prelu", 4)
    norm, act, x = make(bn, act, torch.randn(2, 4, 6, 8))
    assert batch_norm.with_activation(x, norm, act) is None
    assert calls == []


def test_fredsnet_training_fuses_its_activations(monkeypatch):
    # ConvNormAct and the Fourier blocks' parts run batch norm and PReLU/ReLU in one native forward and backward
    from omnidl.models.fredsnet import FreDSNet
    codes = []
    lib = native.library()
    real = lib.omnidl_bn_train

    def counted(*args):
        codes.append(args[13])
        return real(*args)
    monkeypatch.setattr(lib, "omnidl_bn_train", counted)
    model = FreDSNet(backbone="resnet18", width=0.25).train()
    sum(v.float().mean() for v in model(torch.rand(1, 3, 64, 128)).values()).backward()
    assert codes.count(2) >= 20 and codes.count(0) >= 10, codes
