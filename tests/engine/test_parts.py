"""Sampler, schedules, checkpoints, launch helpers."""
import math

import pytest
import torch
from omegaconf import OmegaConf
from torch.utils.data import DistributedSampler

from omnidl.engine.checkpoint import load_checkpoint, load_model_weights, save_checkpoint
from omnidl.engine.config import SchedConfig
from omnidl.engine.launch import prepare_argv
from omnidl.engine.optim import build_optimizer, build_scheduler, lr_factor
from omnidl.engine.sampler import ResumableDistributedSampler
from omnidl.engine.seed import rng_state, seed_everything, set_rng_state


@pytest.mark.parametrize("world", [1, 2, 3])
def test_sampler_matches_torch_distributed_sampler(world):
    ds = list(range(11))
    for rank in range(world):
        ours = ResumableDistributedSampler(len(ds), shuffle=True, seed=5, rank=rank, world_size=world)
        ref = DistributedSampler(ds, num_replicas=world, rank=rank, shuffle=True, seed=5)
        for epoch in (0, 3):
            ours.set_epoch(epoch)
            ref.set_epoch(epoch)
            assert list(ours) == list(ref)
        ours.set_start(2)
        assert list(ours) == list(ref)[2:] and len(ours) == len(ref) - 2


def test_lr_schedules_closed_form():
    cos = OmegaConf.structured(SchedConfig(name="cosine", warmup_steps=4, min_lr_ratio=0.1))
    assert [lr_factor(s, 14, cos) for s in range(4)] == [1 / 5, 2 / 5, 3 / 5, 4 / 5]
    assert lr_factor(4, 14, cos) == pytest.approx(1.0)
    assert lr_factor(9, 14, cos) == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 0.5)))
    assert lr_factor(14, 14, cos) == pytest.approx(0.1)
    step = OmegaConf.structured(SchedConfig(name="step", step_size=3, gamma=0.5))
    assert [lr_factor(s, 10, step) for s in range(7)] == [1, 1, 1, 0.5, 0.5, 0.5, 0.25]
    with pytest.raises(ValueError, match="sched.name"):
        lr_factor(0, 10, OmegaConf.structured(SchedConfig(name="linear")))


def test_scheduler_steps_optimizer_lr():
    p = torch.nn.Parameter(torch.zeros(1))
    opt = build_optimizer([p], OmegaConf.create({"name": "sgd", "lr": 0.2, "momentum": 0.0, "weight_decay": 0.0}))
    sch = build_scheduler(opt, OmegaConf.structured(SchedConfig(name="step", step_size=2, gamma=0.1)), 10)
    lrs = []
    for _ in range(5):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sch.step()
    assert lrs == pytest.approx([0.2, 0.2, 0.02, 0.02, 0.002])
    with pytest.raises(ValueError, match="optim.name"):
        build_optimizer([p], OmegaConf.create({"name": "lion", "lr": 1.0}))


def test_checkpoint_roundtrip_atomic_and_clear_errors(tmp_path):
    m = torch.nn.Linear(3, 2)
    path = save_checkpoint(tmp_path / "c" / "last.pt", {"model": m.state_dict(), "step": 7})
    assert [p.name for p in path.parent.iterdir()] == ["last.pt"]  # no temp files left behind
    ck = load_checkpoint(path)
    assert ck["step"] == 7 and ck["version"] == 1
    m2 = torch.nn.Linear(3, 2)
    load_model_weights(m2, ck)
    assert torch.equal(m2.weight, m.weight)
    with pytest.raises(RuntimeError, match="missing keys"):
        load_model_weights(torch.nn.Sequential(torch.nn.Linear(3, 2)), ck, path)
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "none.pt")
    (tmp_path / "bad.pt").write_bytes(b"garbage")
    with pytest.raises(RuntimeError, match="could not read"):
        load_checkpoint(tmp_path / "bad.pt")
    torch.save(m.state_dict(), tmp_path / "bare.pt")  # a bare state dict is accepted
    load_model_weights(m2, load_checkpoint(tmp_path / "bare.pt"))


def test_rng_state_roundtrip():
    seed_everything(1)
    st = rng_state()
    a = (torch.rand(3), __import__("numpy").random.rand(2), __import__("random").random())
    set_rng_state(st)
    b = (torch.rand(3), __import__("numpy").random.rand(2), __import__("random").random())
    assert torch.equal(a[0], b[0]) and (a[1] == b[1]).all() and a[2] == b[2]


def test_torchrun_argv_shares_run_dir(monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "abc")
    argv = prepare_argv(["train.py", "model=x"])
    assert any(a.startswith("hydra.run.dir=outputs/torchrun/") and a.endswith("/abc") for a in argv)
    assert "hydra.output_subdir=null" in argv
    monkeypatch.setenv("WORLD_SIZE", "1")
    assert prepare_argv(["train.py"]) == ["train.py"]
