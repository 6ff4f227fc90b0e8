"""The model contract, compiled: ``torch.compile(..., fullgraph=True)`` captures every registered model whole, and a
training step through the capture matches eager (tests/models/test_all_models.py has the rest of the contract).

A separate file so that the two suite workers (pytest-xdist, one file at a time) share the contract's slowest tests.
The training-step capture runs once per model, in its projected mode where it has one: that mode holds every module
of the standard one except the swapped convolutions, which are stock ``nn.Conv2d``, plus omnidl's registered
operators and their autograd formulas. The standard modes are captured whole by ``torch.export``
(tests/models/test_export.py) and ``torch.fx`` (test_all_models.py).
"""
from __future__ import annotations

import pytest
import torch

from .test_all_models import VARIANTS, assert_outputs_close, build, floats, without_dropout

ONE_PER_MODEL = [(name, conv) for name, conv in VARIANTS if conv in (None, "projected")]
ONE_PER_MODEL_IDS = [name if conv is None else f"{name}-{conv}" for name, conv in ONE_PER_MODEL]


@pytest.mark.parametrize("name,conv", ONE_PER_MODEL, ids=ONE_PER_MODEL_IDS)
def test_compile_fullgraph_training_step_matches_eager(name, conv):
    """Dynamo captures the whole model as one graph (``fullgraph=True``), forward and backward through AOT autograd
    (backend ``aot_eager``: the capture without Inductor's code generation, which ``test_inductor_compile_matches_eager``
    covers). In float64, so that the comparison measures the capture, not float32 summation order through fifty layers
(a first-layer gradient differs by ~6e-5 in float32 when AOT autograd reorders a reduction). ``nn.LSTM`` (HorizonNet)
needs Dynamo's ``allow_rnn``, which ``trainer.compile`` sets too."""
    torch._dynamo.reset()
    model, x = build(name, conv)
    model, x = without_dropout(model).double().train(), x.double()
    compiled = torch.compile(model, fullgraph=True, dynamic=False, backend="aot_eager")
    results = []
    with torch._dynamo.config.patch(allow_rnn=True):
        for net in (model, compiled):
            model.zero_grad(set_to_none=True)
            out = floats(net(x))
            sum(v.float().square().mean() for v in out.values()).backward()
            results.append((out, {n: p.grad for n, p in model.named_parameters() if p.grad is not None}))
    (eager, eager_grads), (comp, comp_grads) = results
    assert_outputs_close(comp, eager, f"{name}: compiled training forward vs eager")
    assert set(comp_grads) == set(eager_grads)
    for n in eager_grads:
        torch.testing.assert_close(comp_grads[n], eager_grads[n], atol=1e-5, rtol=1e-4,
                                   msg=lambda m: f"{name}: gradient of {n}: {m}")


@pytest.mark.slow
@pytest.mark.parametrize("conv", ["standard", "projected"])
def test_inductor_compile_matches_eager(conv):
    """Through Inductor (the default backend of ``trainer.compile`` and ``omnidl predict --compile``) the registered
    ops run as extern kernels beside the generated code: a forward and a training step of the U-Net (the smallest
    registered model: Inductor's code generation of FreDSNet takes minutes on a 2-core CPU)."""
    torch._dynamo.reset()
    model, x = build("unet", conv)
    compiled = torch.compile(model, fullgraph=True, dynamic=False)
    model.eval()
    with torch.no_grad():
        assert_outputs_close(compiled(x), model(x), "inductor forward vs eager", atol=1e-4, rtol=1e-3)
    model.train()
    losses = [sum(v.square().mean() for v in floats(net(x)).values()) for net in (model, compiled)]
    torch.testing.assert_close(losses[1], losses[0], atol=1e-4, rtol=1e-3)
    losses[1].backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters() if p.requires_grad)
