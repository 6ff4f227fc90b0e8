"""The horizon plane of a panorama from horizon-line and vertical-vanishing-point probability maps
(HoLiNet's outputs, thesis §6.2.1): vertical direction + RANSAC great-circle fit on the sphere.

1. *Vertical direction* from the vanishing-point map: 1-point RANSAC for the axis through the high-VP
   pixels (both poles vote for the same axis), refined by the principal eigenvector of their weighted
   scatter matrix. The sign (zenith vs nadir) comes from the asymmetry of the map: the ground truth of
   :func:`omnidl.data.horizon.horizon_heatmaps` gives the nadir a lower peak, so the heavier pole is
   up. If the two poles weigh the same (a symmetric map, as in the reference code) the up vector is the
   one pointing to the image's upper half (``n_y < 0``), i.e. tilts are folded into [0, 90°].
2. *Horizon plane* from the horizon map: RANSAC over 2-point great-circle hypotheses
   ``n = v1 x v2`` with a coherence test against the vertical direction ``g``:

   * ``coherence="thesis"`` (default): hypotheses with ``angle(n, ±g) > coherence_deg`` (30°) are rejected;
   * ``coherence="reference"``: as coded in the public HoLiNet, hypotheses with ``|n . g| < 0.7`` keep
     half of their vote (down-weighting, ~45.6°);
   * ``coherence="none"``.

   The best plane is refined by weighted least squares (smallest eigenvector of the heat-weighted
   scatter of the pixels in a band around it, solid-angle weights ``cos(lat)``), iterated.
3. The plane normal, oriented like ``g``, is the up vector ``n`` of the camera:
   ``roll, pitch = tilt_from_up(n)`` (:mod:`omnidl.geometry.rotations`).

All directions are in the camera frame (OpenCV); maps are full-sphere equirectangular ``(B, 1, H, W)``
whose pixel directions come from :class:`~omnidl.cameras.Equirectangular`. Pure maths on the maps: the
``horizon`` post-processing hook (:mod:`omnidl.postprocess.gyroscope.horizon`), the gyroscope and the
horizon metric (:mod:`omnidl.metrics.rotation`) all call :func:`fit_horizon`.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from omnidl.cameras.equirectangular import Equirectangular

from .rotations import tilt_from_up, up_vector


@dataclass(frozen=True)
class HorizonFitOptions:
    """Thresholds of :func:`fit_horizon` (angles in degrees, map thresholds relative to the map maximum)."""

    coherence: str = "thesis"          # "thesis" (hard, coherence_deg) | "reference" (0.7, x0.5) | "none"
    coherence_deg: float = 30.0
    reference_cos: float = 0.7
    vp_threshold: float = 0.5          # VP candidates: map > vp_threshold * max
    vp_inlier_deg: float = 20.0
    hl_threshold: float = 0.5          # horizon candidates: map > hl_threshold * max
    hl_inlier_deg: float | None = None  # RANSAC inlier band; default 1.5 output pixels
    refine_band_deg: float | None = None  # refinement band; default 4 output pixels
    refine_iters: int = 3
    hypotheses: int = 256
    max_candidates: int = 4096
    sign_ratio: float = 1.2            # zenith mass / nadir mass needed to trust the VP sign
    min_pair_deg: float = 30.0         # RANSAC samples: two candidates at least this far apart (and from antipodal)
    min_support: float = 0.3           # best plane must gather this fraction of the candidate weight
    seed: int = 0

    def __post_init__(self) -> None:
        if self.coherence not in ("thesis", "reference", "none"):
            raise ValueError(f"horizon fit: coherence must be 'thesis', 'reference' or 'none', got "
                             f"{self.coherence!r}")


def _principal(v: Tensor, w: Tensor, smallest: bool) -> Tensor:
    """Eigenvector of the weighted scatter ``sum w v v^T`` (largest or smallest eigenvalue) of ``v (N, 3)``,
    ``w (N,)``; a subset is given by zero weights (two ops instead of a boolean gather of ``v`` and ``w``)."""
    _, vecs = torch.linalg.eigh((v * w[:, None]).T @ v)
    return vecs[:, 0] if smallest else vecs[:, -1]


def _vertical(dirs: Tensor, vp: Tensor, area: Tensor, o: HorizonFitOptions, gen: torch.Generator) -> tuple[Tensor, bool]:
    """Up direction ``(3,)`` from one VP map ``vp (N,)`` (values relative to its max)."""
    cand = vp > o.vp_threshold
    if int(cand.sum()) == 0:
        return up_vector(dirs), False
    cv, cw = dirs[cand], (vp * area)[cand]
    if len(cv) > o.max_candidates:
        keep = torch.randperm(len(cv), generator=gen)[: o.max_candidates].to(cv.device)
        cv, cw = cv[keep], cw[keep]
    hyp = cv[torch.randperm(len(cv), generator=gen)[: o.hypotheses].to(cv.device)]
    cos_in = math.cos(math.radians(o.vp_inlier_deg))
    inl = (hyp @ cv.T).abs() > cos_in
    score = (inl * cw).sum(-1)
    g = hyp[score.argmax()]
    for _ in range(2):
        g = _principal(cv, cw * ((cv @ g).abs() > cos_in), smallest=False)
    # sign: the zenith peak is the heavier one
    w_all = vp * area
    s = dirs @ g
    plus, minus = w_all[s > cos_in].sum(), w_all[s < -cos_in].sum()
    if plus > o.sign_ratio * minus:
        return g, True
    if minus > o.sign_ratio * plus:
        return -g, True
    return (g if float(g[1]) <= 0 else -g), True


def _plane(dirs: Tensor, hl: Tensor, area: Tensor, g: Tensor, g_ok: bool, pix: float, o: HorizonFitOptions,
           gen: torch.Generator) -> tuple[Tensor, bool]:
    cand = hl > o.hl_threshold
    if int(cand.sum()) < 2:
        return g, False
    cv, cw = dirs[cand], (hl * area)[cand]
    if len(cv) > o.max_candidates:
        keep = torch.randperm(len(cv), generator=gen)[: o.max_candidates].to(cv.device)
        cv, cw = cv[keep], cw[keep]
    i = torch.randint(len(cv), (o.hypotheses,), generator=gen).to(cv.device)
    j = torch.randint(len(cv), (o.hypotheses,), generator=gen).to(cv.device)
    cr = torch.linalg.cross(cv[i], cv[j], dim=-1)
    nrm = cr.norm(dim=-1)
    ok = nrm > math.sin(math.radians(o.min_pair_deg))  # well-conditioned pairs only (not close/antipodal)
    hyp = cr / nrm.clamp_min(1e-12)[:, None]
    band = math.sin(math.radians(o.hl_inlier_deg) if o.hl_inlier_deg is not None else 1.5 * pix)
    inl = (hyp @ cv.T).abs() < band
    score = (inl * cw).sum(-1)
    if g_ok and o.coherence != "none":
        c = (hyp @ g).abs()
        if o.coherence == "thesis":
            ok = ok & (c >= math.cos(math.radians(o.coherence_deg)))
        else:
            score = torch.where(c < o.reference_cos, 0.5 * score, score)
    score = torch.where(ok, score, torch.full_like(score, -1.0))
    if float(score.max()) <= o.min_support * float(cw.sum()):
        return g, False
    n = hyp[score.argmax()]
    rband = math.sin(math.radians(o.refine_band_deg) if o.refine_band_deg is not None else 4 * pix)
    w_all = hl * area
    for _ in range(o.refine_iters):
        m = (dirs @ n).abs() < rband
        if int(m.sum()) < 3:
            break
        n_new = _principal(dirs, w_all * m, smallest=True)
        n = n_new * (1.0 if float(n_new @ n) >= 0 else -1.0)
    if float(n @ g) < 0:
        n = -n
    return n, True


@functools.lru_cache(maxsize=8)
def _sphere_grid(H: int, W: int, dtype: torch.dtype, device: str) -> tuple[Tensor, Tensor]:
    """Pixel directions ``(H*W, 3)`` of a full ``H x W`` equirectangular map and their ``cos(latitude)``
    ``(H*W,)`` (cached: a gyroscope fits every frame on the same grid; callers only read them)."""
    dirs = Equirectangular(width=W, height=H).unproject_grid(dtype, device).direction.reshape(-1, 3)
    return dirs, torch.sqrt((1 - dirs[:, 1] ** 2).clamp_min(0))


def fit_horizon(horizon: Tensor, vp: Tensor, options: HorizonFitOptions | None = None, **overrides) -> dict[str, Tensor]:
    """Fit the horizon plane to probability maps.

    Args:
        horizon, vp: ``(B, 1, H, W)`` (or ``(B, H, W)``) heat maps in ``[0, 1]`` (after the sigmoid) on a
            full equirectangular grid.
        options / overrides: :class:`HorizonFitOptions` fields.
    Returns:
        ``{"up": (B, 3) horizon normal (camera frame, pointing to the zenith), "vertical": (B, 3) VP
        direction, "roll": (B,), "pitch": (B,) radians, "valid": (B,) bool}``. ``valid`` is False when
        the maps hold no usable line (then ``up`` falls back to the VP direction, or to upright).
    """
    o = options or HorizonFitOptions()
    if overrides:
        o = HorizonFitOptions(**{**o.__dict__, **overrides})
    if horizon.ndim == 3:
        horizon = horizon.unsqueeze(1)
    if vp.ndim == 3:
        vp = vp.unsqueeze(1)
    if horizon.shape != vp.shape or horizon.ndim != 4 or horizon.shape[1] != 1:
        raise ValueError(f"fit_horizon: expected horizon and vp maps of the same shape (B, 1, H, W), got "
                         f"{tuple(horizon.shape)} and {tuple(vp.shape)}")
    B, _, H, W = horizon.shape
    dtype = horizon.dtype if horizon.dtype == torch.float64 else torch.float32
    dirs, area = _sphere_grid(H, W, dtype, str(horizon.device))
    pix = math.pi / H
    gen = torch.Generator().manual_seed(o.seed)
    ups, verts, valid = [], [], []
    for b in range(B):
        hl = horizon[b, 0].reshape(-1).to(dtype)
        vv = vp[b, 0].reshape(-1).to(dtype)
        if not (torch.isfinite(hl).all() and torch.isfinite(vv).all()):
            raise ValueError("fit_horizon: heat maps contain NaN/inf values")
        hmax, vmax = float(hl.max()), float(vv.max())
        if vmax > 1e-6:
            g, g_ok = _vertical(dirs, vv / vmax, area, o, gen)
        else:
            g, g_ok = up_vector(dirs), False
        if hmax > 1e-6:
            n, ok = _plane(dirs, hl / hmax, area, g, g_ok, pix, o, gen)
        else:
            n, ok = g, False
        ups.append(n)
        verts.append(g)
        valid.append(ok)
    up = torch.stack(ups)
    roll, pitch = tilt_from_up(up)
    return {"up": up, "vertical": torch.stack(verts), "roll": roll, "pitch": pitch,
            "valid": torch.tensor(valid, device=horizon.device)}
