"""The channels-last policy of FreDSNet and HoLiNet: per mode, same parameters, same results."""
from __future__ import annotations

import pytest
import torch

from omnidl.models import create_model

SMALL = {"fredsnet": dict(name="fredsnet", backbone="resnet18", width=0.125),
         "holinet": dict(name="holinet", backbone="resnet18", width=0.125)}


def _conv_weights(model):
    return [p for p in model.parameters() if p.dim() == 4]


def _is_cl(model) -> bool:
    ws = _conv_weights(model)
    cl = [w.is_contiguous(memory_format=torch.channels_last) and not w.is_contiguous() for w in ws
          if w.shape[2] * w.shape[3] > 1 and w.shape[1] > 1]
    assert cl and (all(cl) or not any(cl)), "conv weights in mixed memory formats"
    return cl[0]


@pytest.mark.parametrize("name", sorted(SMALL))
def test_auto_is_nchw_in_training_and_channels_last_in_eval_for_dense_convolutions(name):
    torch.manual_seed(0)
    m = create_model(conv="standard", **SMALL[name])
    params = list(m.parameters())
    assert m.channels_last == "auto" and m.training and not _is_cl(m) and not m.uses_channels_last
    m.eval()
    assert _is_cl(m) and m.uses_channels_last
    m.train()
    assert not _is_cl(m)
    assert all(a is b for a, b in zip(params, m.parameters()))  # the same Parameter objects (optimisers)


def test_auto_trains_projected_convolutions_in_nchw_too():
    m = create_model(conv="projected", **SMALL["holinet"])
    assert m.training and not _is_cl(m)
    m.eval()
    assert _is_cl(m)


@pytest.mark.parametrize("name", sorted(SMALL))
def test_outputs_agree_across_policies_and_modes(name):
    torch.manual_seed(1)
    x = torch.rand(1, 3, 64, 128)
    models = {}
    for policy in (True, False, "auto"):
        torch.manual_seed(0)
        models[policy] = create_model(conv="standard", channels_last=policy, **SMALL[name]).eval()
    with torch.no_grad():
        outs = {k: m(x) for k, m in models.items()}
    for k in (False, "auto"):
        for key, v in outs[True].items():
            assert (outs[k][key] - v).abs().max() <= 1e-4 * max(1.0, float(v.abs().max())), (k, key)


def test_training_flag_set_directly_is_honoured_at_forward():
    torch.manual_seed(0)
    m = create_model(conv="standard", **SMALL["fredsnet"]).eval()
    assert _is_cl(m)
    m.training = True  # without train(): the forward re-checks the mode
    m(torch.rand(1, 3, 64, 128))
    assert not _is_cl(m)


def test_optimizer_keeps_working_across_mode_switches():
    torch.manual_seed(0)
    m = create_model(conv="standard", **SMALL["fredsnet"])
    opt = torch.optim.Adam(m.parameters(), lr=1e-3)
    x = torch.rand(2, 3, 64, 128)
    for _ in range(2):
        m.train()
        opt.zero_grad()
        out = m(x)
        (out["depth"].mean() + out["semantic"].mean()).backward()
        opt.step()
        m.eval()
        with torch.no_grad():
            assert torch.isfinite(m(x)["depth"]).all()


@pytest.mark.parametrize("name", sorted(SMALL))
def test_bad_policy_is_a_clear_error(name):
    with pytest.raises(ValueError, match="channels_last must be true, false or 'auto', got 'yes'"):
        create_model(channels_last="yes", **SMALL[name])
