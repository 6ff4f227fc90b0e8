"""Tiny stand-ins for the engine tests: a 2-layer model, a random panorama dataset, a loss and metrics
that follow docs/extending.md. Referenced from configs by ``_target_: engine_standins.<name>``."""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

NUM_CLASSES = 4


class TinyNet(nn.Module):
    def __init__(self, num_classes: int = NUM_CLASSES, width: int = 8, dropout: float = 0.1):
        super().__init__()
        self.conv1 = nn.Conv2d(3, width, 3, padding=1)
        self.drop = nn.Dropout2d(dropout)
        self.conv2 = nn.Conv2d(width, 1 + num_classes, 3, padding=1)

    def forward(self, x):
        y = self.conv2(self.drop(F.relu(self.conv1(x))))
        return {"depth": F.softplus(y[:, :1]), "semantic": y[:, 1:]}


class RandomPanoramas(torch.utils.data.Dataset):
    """Deterministic random samples: depth = 1 + 2*mean colour, semantics = brightest channel (learnable)."""

    def __init__(self, length: int = 12, height: int = 16, width: int = 32, seed: int = 0, nan_index: int = -1):
        self.length, self.h, self.w, self.seed, self.nan_index = length, height, width, seed, nan_index

    def __len__(self):
        return self.length

    def __getitem__(self, i):
        g = torch.Generator().manual_seed(self.seed * 10007 + i)
        img = torch.rand(3, self.h, self.w, generator=g)
        depth = 1 + 2 * img.mean(0, keepdim=True)
        sem = img.argmax(0) + 1
        sem[0, :] = 0  # unknown row
        if i == self.nan_index:
            img = img.clone()
            img[0, 0, 0] = float("nan")
        return {"image": img, "depth": depth, "semantic": sem, "meta": {"index": i, "name": f"sample_{i:03d}"}}


class SimulatedKill(RuntimeError):
    pass


class CorruptPanoramas(torch.utils.data.Dataset):
    """Every sample is unreadable (``CorruptSampleError`` naming a file), like a folder of Git-LFS pointers."""

    def __init__(self, length: int = 40):
        self.length = length

    def __len__(self):
        return self.length

    def __getitem__(self, i):
        from omnidl.data.robust import CorruptSampleError
        raise CorruptSampleError(f"could not read image rgb/pointer_{i:03d}.png (truncated)")


class TinyLoss(nn.Module):
    """L1 depth + cross entropy; ``kill_at=k`` raises :class:`SimulatedKill` on the k-th training call;
    ``sleep``: seconds to wait per training call (gives a subprocess test time to send a signal)."""

    def __init__(self, kill_at: int = 0, sleep: float = 0.0):
        super().__init__()
        self.kill_at, self.calls, self.sleep = kill_at, 0, sleep

    def forward(self, outputs, batch):
        if torch.is_grad_enabled():
            self.calls += 1
            if self.sleep:
                __import__("time").sleep(self.sleep)
            if self.kill_at and self.calls == self.kill_at:
                raise SimulatedKill(f"killed at training call {self.calls}")
        valid = batch["depth"] > 0
        l_depth = (outputs["depth"] - batch["depth"]).abs()[valid].mean()
        l_sem = F.cross_entropy(outputs["semantic"], batch["semantic"], ignore_index=0)
        return l_depth + l_sem, {"depth": float(l_depth.detach()), "semantic": float(l_sem.detach())}


class TinyMetrics:
    def __init__(self):
        self.reset()

    def reset(self):
        self.abs, self.n, self.correct, self.total = 0.0, 0, 0, 0

    def update(self, outputs, batch):
        valid = batch["depth"] > 0
        self.abs += float((outputs["depth"] - batch["depth"]).abs()[valid].sum())
        self.n += int(valid.sum())
        known = batch["semantic"] > 0
        pred = outputs["semantic"].argmax(1) + 0
        self.correct += int((pred == batch["semantic"])[known].sum())
        self.total += int(known.sum())

    def compute(self):
        return {"mae": self.abs / max(self.n, 1), "acc": self.correct / max(self.total, 1)}


#: (hook options) of every call of the ``engine_test_scaled_depth`` hook (tests/engine/test_hooks.py)
HOOK_CALLS: list[dict] = []


def scaled_depth_hook(outputs, batch, scale=1.0, export_dir=None):
    """A post-processing hook stand-in: ``{"scaled_depth": scale * depth, "hook_calls": n}``."""
    HOOK_CALLS.append({"scale": scale, "export_dir": export_dir})
    return {"scaled_depth": outputs["depth"] * scale, "hook_calls": len(HOOK_CALLS)}


class HookMetrics:
    """Reads a hook product: the mean of ``outputs["scaled_depth"]`` (a KeyError without the hook)."""

    def __init__(self):
        self.reset()

    def reset(self):
        self.sum, self.n = 0.0, 0

    def update(self, outputs, batch):
        self.sum += float(outputs["scaled_depth"].sum())
        self.n += outputs["scaled_depth"].numel()

    def compute(self):
        return {"scaled_depth": self.sum / max(self.n, 1)}
