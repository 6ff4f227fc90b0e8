"""The ``channels_last`` option of the models: chosen once at construction, the same in every mode, same results."""
from __future__ import annotations

import pytest
import torch

from omnidl.models import create_model

SMALL = {"fredsnet": dict(name="fredsnet", backbone="resnet18", width=0.125),
         "holinet": dict(name="holinet", backbone="resnet18", width=0.125, conv="standard"),
         "horizonnet": dict(name="horizonnet", backbone="resnet18", hidden=16)}


def _is_cl(model) -> bool:
    ws = [p for p in model.parameters() if p.dim() == 4 and p.shape[2] * p.shape[3] > 1 and p.shape[1] > 1]
    cl = [w.is_contiguous(memory_format=torch.channels_last) and not w.is_contiguous() for w in ws]
    assert cl and (all(cl) or not any(cl)), "conv weights in mixed memory formats"
    return cl[0]


@pytest.mark.parametrize("name", sorted(SMALL))
def test_the_format_is_chosen_once_and_outputs_agree(name):
    """The memory format changes where numbers lie, not what is computed: equal outputs in float64 (float32's
    rounding differs by the order of the sums, and FreDSNet's spectral paths amplify it)."""
    torch.manual_seed(0)
    models = {cl: create_model(channels_last=cl, **SMALL[name]).double() for cl in (False, True)}
    models[True].load_state_dict(models[False].state_dict())
    x = torch.rand(2, 3, 32, 64, dtype=torch.float64)
    outs = {}
    for train in (False, True):
        for cl, m in models.items():
            m.train(train)
            assert _is_cl(m) == cl                                    # no switch by mode
            outs[cl, train] = m(x)
    for k, v in outs[False, False].items():                           # eval (before training touched the stats)
        torch.testing.assert_close(outs[True, False][k], v, atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize("name", sorted(SMALL))
@pytest.mark.parametrize("bad", ["yes", "auto", 2])
def test_bad_value_is_a_clear_error(name, bad):
    with pytest.raises(ValueError, match=f"channels_last must be true or false, got {bad!r}"):
        create_model(channels_last=bad, **SMALL[name])
