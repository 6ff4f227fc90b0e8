"""The model contract (docs/extending.md, "Models: the contract"), run on every registered model in each of its
convolution modes (``conv="standard"`` and ``conv="projected"`` where the model has the switch).

One network in every mode: train, eval with grad and eval under ``torch.no_grad()`` run the same modules (forward
hooks see every one); a swapped norm takes effect in all three; ``torch.fx.symbolic_trace``, ``torch.compile(...,
fullgraph=True)`` (tests/models/test_all_models_compile.py) and ``torch.export`` (tests/models/test_export.py) take the
model as it is.
"""
from __future__ import annotations

import pytest
import torch
from torch import nn

from omnidl.models import create_model, list_models
from omnidl.models.registry import smoke_config


def _has_conv_switch(name: str) -> bool:
    try:
        create_model(name, **dict(smoke_config(name)["kwargs"], conv="standard"))
    except TypeError as e:
        if "conv" in str(e):
            return False
        raise
    return True


VARIANTS = [(name, conv) for name in list_models()
            for conv in (("standard", "projected") if _has_conv_switch(name) else (None,))]
IDS = [name if conv is None else f"{name}-{conv}" for name, conv in VARIANTS]


def build(name: str, conv: str | None, seed: int = 0) -> tuple[nn.Module, torch.Tensor]:
    """The smoke configuration of ``name`` in ``conv`` mode (projected: an equirectangular camera of the input
    size) and a batch of two inputs."""
    cfg = smoke_config(name)
    kwargs = dict(cfg["kwargs"])
    h, w = cfg["size"]
    if conv is not None:
        kwargs["conv"] = conv
    if conv == "projected":
        kwargs["camera"] = {"type": "equirect", "width": w, "height": h}
    torch.manual_seed(seed)
    model = create_model(name, **kwargs)
    x = torch.rand(2, 3, h, w, generator=torch.Generator().manual_seed(seed + 1))
    return model, x


def floats(out: dict) -> dict[str, torch.Tensor]:
    return {k: v for k, v in out.items() if isinstance(v, torch.Tensor) and v.is_floating_point()}


def assert_outputs_close(a: dict, b: dict, what: str, atol: float = 1e-5, rtol: float = 1e-4) -> None:
    a, b = floats(a), floats(b)
    assert set(a) == set(b), f"{what}: outputs {sorted(a)} vs {sorted(b)}"
    for k in a:
        torch.testing.assert_close(a[k], b[k], atol=atol, rtol=rtol, msg=lambda m: f"{what}, output {k!r}: {m}")


def without_dropout(model: nn.Module) -> nn.Module:
    """``model`` with every dropout a no-op (modules replaced by ``nn.Identity``, LSTM dropout 0)."""
    for parent in list(model.modules()):
        for child_name, child in list(parent.named_children()):
            if isinstance(child, nn.modules.dropout._DropoutNd):
                setattr(parent, child_name, nn.Identity())
            elif isinstance(child, nn.RNNBase):
                child.dropout = 0.0
    return model


def swap_norms(model: nn.Module) -> int:
    """Replace every batch norm by a ``GroupNorm(1, C)``; the number replaced."""
    n = 0
    for parent in list(model.modules()):
        for child_name, child in list(parent.named_children()):
            if isinstance(child, nn.modules.batchnorm._BatchNorm):
                setattr(parent, child_name, nn.GroupNorm(1, child.num_features))
                n += 1
    return n


MODES = ("train", "eval, grad", "eval, no_grad")


def run(model: nn.Module, x: torch.Tensor, mode: str) -> dict:
    model.train(mode == "train")
    with torch.set_grad_enabled(mode != "eval, no_grad"):
        return model(x)


@pytest.mark.parametrize("name,conv", VARIANTS, ids=IDS)
def test_forward_backward_every_parameter_gets_gradient(name, conv):
    model, x = build(name, conv)
    model.train()
    out = model(x)
    assert isinstance(out, dict) and out, "forward must return a non-empty dict of named outputs"
    total = 0
    for key, val in floats(out).items():
        assert torch.isfinite(val).all(), f"{name}: output {key!r} has non-finite values"
        total = total + val.float().mean()
    total.backward()
    missing = [n for n, p in model.named_parameters()
               if p.requires_grad and (p.grad is None or not torch.isfinite(p.grad).all())]
    assert not missing, f"{name}: parameters without a finite gradient: {missing[:10]}"


@pytest.mark.parametrize("name,conv", VARIANTS, ids=IDS)
def test_same_modules_and_hooks_in_every_mode(name, conv):
    model, x = build(name, conv)
    calls: list[str] = []
    for module_name, module in model.named_modules():
        module.register_forward_hook(lambda m, i, o, module_name=module_name: calls.append(module_name))
    seen = {}
    for mode in MODES:
        calls.clear()
        run(model, x, mode)
        seen[mode] = list(calls)
    assert seen["eval, grad"] == seen["train"], f"{name}: eval with grad runs other modules than training"
    assert seen["eval, no_grad"] == seen["train"], f"{name}: eval without grad runs other modules than training"
    leaves = {n for n, m in model.named_modules() if not list(m.children()) and list(m.parameters(recurse=False))}
    assert leaves <= set(seen["train"]), f"{name}: modules with parameters never called: {sorted(leaves - set(calls))}"


@pytest.mark.parametrize("name,conv", VARIANTS, ids=IDS)
def test_swapped_norm_takes_effect_in_every_mode(name, conv):
    model, x = build(name, conv)
    without_dropout(model)
    before = run(model, x, "eval, no_grad")
    assert swap_norms(model) > 0, f"{name}: no batch norm to swap"
    fired = []
    for m in model.modules():
        if isinstance(m, nn.GroupNorm):
            m.register_forward_hook(lambda *_: fired.append(1))
    outs = {}
    for mode in MODES:
        fired.clear()
        outs[mode] = run(model, x, mode)
        assert fired, f"{name}: the swapped norms did not run in mode {mode!r}"
    # GroupNorm has no running statistics and dropout is off: the three modes compute one function
    assert_outputs_close(outs["eval, grad"], outs["train"], f"{name}: eval with grad vs train")
    assert_outputs_close(outs["eval, no_grad"], outs["train"], f"{name}: eval without grad vs train")
    changed = [k for k, v in floats(before).items() if not torch.allclose(v, outs["eval, no_grad"][k])]
    assert changed, f"{name}: swapping the norms left every output unchanged"


@pytest.mark.parametrize("name,conv", VARIANTS, ids=IDS)
def test_fx_symbolic_trace(name, conv):
    model, x = build(name, conv)
    model.eval()
    traced = torch.fx.symbolic_trace(model)
    with torch.no_grad():
        assert_outputs_close(traced(x), model(x), f"{name}: fx-traced vs eager")


@pytest.mark.parametrize("name,conv", VARIANTS, ids=IDS)
def test_integer_images_are_refused(name, conv):
    """A ``uint8`` image (0..255) is refused with a message naming the dtype, never normalised in uint8."""
    model, x = build(name, conv)
    with pytest.raises(ValueError, match="floating-point image.*uint8"):
        model.eval()(x.mul(255).to(torch.uint8))
