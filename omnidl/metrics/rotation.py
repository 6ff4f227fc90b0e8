"""Rotation metrics of the visual gyroscope (thesis §6.3.1).

* horizon-normal error: the angle ``arccos(n . n_gt)`` between the estimated and true horizon-plane
  normals (up vectors, camera frame), degrees. Signed normals, so an upside-down estimate counts 180°
  (``sign_agnostic=True`` gives ``arccos|n . n_gt|``, the reference code's folded view);
* 3-DoF rotation error ``arccos((tr(R_gt R_est^T) - 1) / 2)``, degrees (computed with ``atan2`` for accuracy);
* success rate: fraction of frames whose error is below a threshold (frames without an estimate fail).

:class:`HorizonMetrics` follows the metrics contract (``reset / update(outputs, batch) / compute``) for a
HoLiNet: it fits the horizon on the sigmoid of ``outputs["horizon"]`` / ``outputs["vp"]`` with the geometry
floor's :func:`~omnidl.geometry.horizon.fit_horizon` (the same function the ``horizon`` post-processing hook
calls) and compares with ``batch["up"]``; it also reports the constant-upright baseline (always
predicting ``(0, -1, 0)``).
:class:`RotationMetrics` compares ``outputs["rotation"]`` with ``batch["rotation"]``.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from omnidl.geometry.horizon import fit_horizon
from omnidl.geometry.rotations import UP, rotation_angle


def horizon_normal_error(n_est: Tensor, n_gt: Tensor, sign_agnostic: bool = False) -> Tensor:
    """``(...)`` angle in degrees between normals ``(..., 3)`` (normalised here)."""
    a = n_est / n_est.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b = n_gt / n_gt.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cos = (a * b).sum(-1)
    sin = torch.linalg.cross(a, b, dim=-1).norm(dim=-1)
    if sign_agnostic:
        cos = cos.abs()
    return torch.rad2deg(torch.atan2(sin, cos))


def rotation_error(R_gt: Tensor, R_est: Tensor) -> Tensor:
    """``(...)`` geodesic angle in degrees, ``arccos((tr(R_gt R_est^T) - 1) / 2)``.

    :func:`omnidl.geometry.rotations.rotation_angle` of ``R_est^T R_gt`` (a conjugate of ``R_gt R_est^T``,
    so the same angle), in its accurate ``atan2`` form.
    """
    return torch.rad2deg(rotation_angle(R_est, R_gt))


def success_rate(errors: Tensor, threshold_deg: float) -> float:
    """Fraction of ``errors`` (degrees; NaN = no estimate, counts as a failure) below ``threshold_deg``."""
    if errors.numel() == 0:
        return math.nan
    ok = torch.isfinite(errors) & (errors < threshold_deg)
    return float(ok.double().mean())


def _summary(prefix: str, err: Tensor, thresholds: Sequence[float]) -> dict[str, float]:
    fin = err[torch.isfinite(err)]
    out = {f"{prefix}_error_mean": float(fin.mean()) if fin.numel() else math.nan,
           f"{prefix}_error_median": float(fin.median()) if fin.numel() else math.nan}
    for t in thresholds:
        out[f"{prefix}_success@{t:g}"] = success_rate(err, t)
    return out


class HorizonMetrics:
    """Mean/median horizon-normal error of HoLiNet outputs, success rates, and the upright baseline.

    Args:
        thresholds: success thresholds in degrees.
        logits: the model outputs logits (sigmoid applied here).
        fit: :class:`~omnidl.geometry.horizon.HorizonFitOptions` overrides.
    Reads ``outputs["horizon"], outputs["vp"]`` ``(B, 1, h, w)`` and ``batch["up"]`` ``(B, 3)``; samples
    with ``batch["geometry_valid"] == False`` (cropped) are skipped. Maps without a usable line count with
    the fit's fallback direction (``horizon_no_line`` gives their fraction).
    """

    def __init__(self, thresholds: Sequence[float] = (5.0, 10.0), logits: bool = True, fit: dict | None = None) -> None:
        self.thresholds = tuple(float(t) for t in thresholds)
        self.logits = logits
        self.fit = dict(fit or {})
        self.reset()

    def reset(self) -> None:
        self.errors: list[Tensor] = []
        self.baseline: list[Tensor] = []
        self.invalid: list[Tensor] = []

    def update(self, outputs: dict, batch: dict) -> None:
        if "up" not in batch:
            raise KeyError(f"HorizonMetrics: the batch has no 'up' ground truth (keys: {sorted(batch)})")
        hl, vp = outputs["horizon"].detach().float(), outputs["vp"].detach().float()
        if self.logits:
            hl, vp = torch.sigmoid(hl), torch.sigmoid(vp)
        gt = batch["up"].detach().float().cpu()
        keep = batch.get("geometry_valid")
        keep = torch.ones(len(gt), dtype=torch.bool) if keep is None else torch.as_tensor(keep).bool().cpu()
        if not bool(keep.any()):
            return
        res = fit_horizon(hl[keep.to(hl.device)].cpu(), vp[keep.to(vp.device)].cpu(), **self.fit)
        # frames without a line keep the fit's fallback (VP direction, else upright) in the error statistics
        self.errors.append(horizon_normal_error(res["up"].float(), gt[keep]))
        self.invalid.append(~res["valid"].cpu())
        up = torch.tensor(UP).expand_as(gt[keep])
        self.baseline.append(horizon_normal_error(up, gt[keep]))

    def compute(self) -> dict[str, float]:
        if not self.errors:
            return {}
        err, base = torch.cat(self.errors), torch.cat(self.baseline)
        out = _summary("horizon", err, self.thresholds)
        out.update(_summary("upright_baseline", base, self.thresholds))
        out["horizon_no_line"] = float(torch.cat(self.invalid).double().mean())
        return out


class RotationMetrics:
    """3-DoF rotation error of ``outputs["rotation"]`` vs ``batch["rotation"]`` (``(B, 3, 3)``), degrees."""

    def __init__(self, thresholds: Sequence[float] = (1.0, 5.0)) -> None:
        self.thresholds = tuple(float(t) for t in thresholds)
        self.reset()

    def reset(self) -> None:
        self.errors: list[Tensor] = []

    def update(self, outputs: dict, batch: dict) -> None:
        R_est = outputs["rotation"].detach().double().cpu()
        R_gt = batch["rotation"].detach().double().cpu()
        if R_est.shape != R_gt.shape or R_est.shape[-2:] != (3, 3):
            raise ValueError(f"RotationMetrics: expected matching (B, 3, 3) rotations, got {tuple(R_est.shape)} "
                             f"and {tuple(R_gt.shape)}")
        err = rotation_error(R_gt, R_est)
        self.errors.append(torch.where(torch.isfinite(R_est).all(-1).all(-1), err, torch.full_like(err, math.nan)))

    def compute(self) -> dict[str, float]:
        if not self.errors:
            return {}
        return _summary("rotation", torch.cat(self.errors), self.thresholds)
