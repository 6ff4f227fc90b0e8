"""The view chain: any camera -> perspective views -> a perspective depth model -> aligned, fused depth on the camera.

A perspective depth network (e.g. Depth-Anything-V2) only sees pinhole images. :func:`depth_through_views` runs it on
any omnidirectional camera of omnidl, central or not:

1. **Views** (:func:`view_layout`): ``V`` square pinhole cameras ``S x S`` with a field of view ``fov`` sharing the
   input camera's centre (the origin of its frame), rotated by ``R_k`` (``R_input_view``: a view-frame direction
   ``d`` is ``R_k @ d`` in the input frame). ``"tangent"``: 12 views towards the vertices of an icosahedron with one
   vertex straight up (``-y``): the poles and two rings of 5 at latitudes ``±26.57°`` (covering radius 37.4°;
   default ``fov`` 100°). ``"cube"``: the 6 faces of :mod:`omnidl.geometry.cubemap` widened to ``fov`` (default
   110°: a 10° overlap on every side). Views upright (image "up" towards ``-y``) except the poles.
2. **Cut** (:func:`cut_views`): every view pixel's direction is projected into the input image and sampled
   (bilinear, the 360° seam wrapped). A non-central input (whose rays do not meet in one point) is sampled where its
   rays see the point at ``assumed_range`` metres along the view ray from the centre (where no ray sees that point,
   e.g. within ``atan(rc / assumed_range)`` of a non-central panorama's poles: farther along the view ray,
   :func:`view_grid`).
3. **Predict**: ``predict(images (V, 3, S, S)) -> (V, 1, S, S)``: z-depth (``kind="depth"``) or an inverse depth
   (``kind="disparity"``) of each view.
4. **Align** (:func:`align_views`): every input pixel seen by two or more views gives one equation per view; the
   per-view ``scale`` (``align="scale"``: least squares on log range, geometric mean of the scales fixed to 1, so a
   metric model keeps its metric scale) or ``scale`` and ``shift`` (``align="affine"``, for affine-invariant inverse
   depth: least squares on inverse range, the mean scale fixed to 1) make all views agree. Residuals beyond 3
   robust standard deviations (and 2 %; depth edges) are dropped and the solve repeated (``robust_iters``).
5. **Fuse** (:class:`FusedViews`): the range along a direction is the weighted mean (of log range, or of inverse
   range) over the views that see it, each weighted by its distance to the view's border (a tent falling to 0 at
   the border: no seam). For a central input the range of pixel ``p`` is the fused range along its ray. For a
   non-central input, pixel ``p`` has its own ray ``o + t d``: ``t`` solves ``|o + t d| = r(dir(o + t d))`` by
   fixed-point iteration (``noncentral_iters``), ``r`` the fused range from the centre; a pixel whose iteration has
   not settled (to 0.1 %) is left invalid (:func:`fuse_on_camera`). Such pixels, and the few wrong ones, lie on depth
   edges: a ray from the rig that sees a point the centre does not (hidden behind a nearer surface) has no exact
   fixed point in the views.

A network trained on the views themselves (:mod:`omnidl.data.views`, the same views and cut, z-depth targets) is a
plain perspective network; :class:`ThroughViews` runs it on whole images of a camera, always through this chain
(``evaluate.py`` wraps it when the data config says ``through_views``).

Depth conventions: the output is the **range along each pixel's ray** from the ray's origin (omnidl's depth maps,
:mod:`omnidl.synth`); views' ``"depth"`` is z-depth along the view's optical axis (what perspective models predict).
Shapes: input image ``(3, H, W)`` or ``(1, 3, H, W)``; outputs ``(1, H, W)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, NamedTuple, Sequence

import torch
from torch import Tensor

from omnidl.cameras.base import Camera
from omnidl.cameras.pinhole import Pinhole
from omnidl.cameras.resolve import resolve_camera

from .cubemap import cube_face_rotations
from .warp import WarpGrid, sample_grid

LAYOUTS = ("tangent", "cube")
DEFAULT_FOV = {"tangent": 100.0, "cube": 110.0}
KINDS = ("depth", "disparity")
ALIGNS = ("scale", "affine", "none")


class View(NamedTuple):
    """One perspective view: a square ``Pinhole`` and ``rotation`` ``R_input_view`` ``(3, 3)`` float64."""

    camera: Pinhole
    rotation: Tensor


def _look_rotation(c: Tensor) -> Tensor:
    """``R_input_view`` whose optical axis (``+z``) is ``c`` and whose ``x`` axis is horizontal (``y`` down)."""
    c = c / c.norm()
    down = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    x = torch.linalg.cross(down, c)
    if float(x.norm()) < 1e-6:  # looking straight up or down
        x = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    x = x / x.norm()
    y = torch.linalg.cross(c, x)
    return torch.stack([x, y, c], dim=1)


def view_layout(layout: str = "tangent", size: int = 518, fov: float | None = None) -> list[View]:
    """The views of ``layout`` (``"tangent"`` or ``"cube"``), ``size x size`` pixels, ``fov`` degrees (module doc)."""
    if layout not in LAYOUTS:
        raise ValueError(f"view layout must be one of {LAYOUTS}, got {layout!r}")
    fov = DEFAULT_FOV[layout] if fov is None else float(fov)
    if not 60.0 <= fov < 170.0:
        raise ValueError(f"view fov must lie in [60, 170) degrees, got {fov}")
    if layout == "tangent" and fov < 2 * 37.38 + 2:
        raise ValueError(f"tangent views need fov >= 77 degrees to cover the sphere with overlap, got {fov}")
    if layout == "cube" and fov <= 90.0:
        raise ValueError(f"cube views need fov > 90 degrees (overlap for the alignment), got {fov}")
    size = int(size)
    if size < 8:
        raise ValueError(f"view size must be >= 8 pixels, got {size}")
    f = 0.5 * size / math.tan(math.radians(fov) / 2)
    cam = Pinhole(width=size, height=size, fx=f, fy=f, cx=size / 2, cy=size / 2)
    if layout == "cube":
        return [View(cam, R) for R in cube_face_rotations(torch.float64)]
    dirs = [torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)]
    lat0 = math.atan(0.5)
    for ring, lat in enumerate((lat0, -lat0)):
        for i in range(5):
            lon = math.radians(72 * i + 36 * ring)
            dirs.append(torch.tensor([math.cos(lat) * math.sin(lon), -math.sin(lat), math.cos(lat) * math.cos(lon)],
                                     dtype=torch.float64))
    return [View(cam, _look_rotation(d)) for d in dirs]


def _input_rays(camera: Camera, dtype: torch.dtype, device) -> tuple[Tensor, Tensor, Tensor]:
    rays = camera.unproject_grid(dtype=torch.float64, device=device)
    return rays.origin.to(dtype), rays.direction.to(dtype), rays.valid


#: a non-central camera's cut: ranges ``assumed_range * FAR_STEP ** k`` (k = 1..FAR_STEPS) tried where no ray sees the
#: point at ``assumed_range`` (up to ``2 ** 12 = 4096`` times farther)
FAR_STEP, FAR_STEPS = 2.0, 12


def view_grid(camera: Camera, view: View, assumed_range: float = 3.0, device=None) -> tuple[Tensor, Tensor]:
    """Where ``camera`` sees each pixel of ``view``: ``uv (S, S, 2)`` float64 input pixels and ``valid (S, S)``.

    A central camera projects each view ray's direction. A non-central one projects the point at ``assumed_range``
    metres along the view ray from the centre; where no ray of the camera sees that point (it lies inside the rig:
    above or below a non-central panorama's circle of radius ``rc``, within ``atan(rc / assumed_range)`` of the
    poles), the point farther along the same view ray (``assumed_range * 2 ** k``, the first ``k <= 12`` a ray sees;
    the limit is the rays closest to the pole). This is the one mapping from a view to the input camera: the
    zero-shot chain (:func:`cut_views`) and the training views (:mod:`omnidl.data.views`) both use it."""
    dist = 1.0 if camera.central else float(assumed_range)
    if not (math.isfinite(dist) and dist > 0):
        raise ValueError(f"cut_views: assumed_range must be a finite number > 0 metres, got {assumed_range}")
    d = view.camera.unproject_grid(dtype=torch.float64, device=device).direction
    d = d @ view.rotation.to(d).T
    uv, ok = camera.project(d * dist)
    if not camera.central:
        for k in range(1, FAR_STEPS + 1):
            if bool(ok.all()):
                break
            far_uv, far_ok = camera.project(d * dist * FAR_STEP ** k)
            take = far_ok & ~ok
            uv = torch.where(take[..., None], far_uv, uv)
            ok = ok | take
    return uv, ok


def view_warp(camera: Camera, view: View, assumed_range: float = 3.0, device=None) -> WarpGrid:
    """:func:`view_grid` as the sampling grid of ``view`` in ``camera``'s image (the 360° seam wrapped where the camera
    wraps): ``sample_grid(image (1, C, H, W), view_warp(...), "bilinear")`` is the view's cut (:func:`cut_views`);
    callers that cut the same view many times keep it."""
    uv, ok = view_grid(camera, view, assumed_range, device)
    return WarpGrid(uv.unsqueeze(0), ok.unsqueeze(0), camera.width, camera.height, camera.wraps_horizontally)


def view_cos(view: View, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
    """``(S, S)`` cosine of each view pixel's ray to the view's optical axis (``+z``). A view's z-depth is
    ``range * view_cos`` (range from the centre along the pixel's ray): the conversion the chain inverts when it
    reads a view's depth as ``z / cos`` (:func:`align_views`, :class:`FusedViews`)."""
    return view.camera.unproject_grid(dtype=dtype, device=device).direction[..., 2]


def cut_views(image: Tensor, camera: Camera, views: Sequence[View], assumed_range: float = 3.0) -> tuple[Tensor, Tensor]:
    """The views' images ``(V, C, S, S)`` and valid masks ``(V, 1, S, S)`` from ``image (C, H, W)`` of ``camera``,
    sampled bilinearly where :func:`view_grid` says the camera sees each view pixel."""
    x = image if image.dim() == 4 else image.unsqueeze(0)
    if x.shape[0] != 1 or x.shape[-2:] != (camera.height, camera.width):
        raise ValueError(f"cut_views: image must be (C, H, W) of the camera's size {camera.height}x{camera.width}, "
                         f"got {tuple(image.shape)}")
    outs, valids = [], []
    for view in views:
        out, valid = sample_grid(x, view_warp(camera, view, assumed_range, x.device), "bilinear")
        outs.append(out[0])
        valids.append(valid[0])
    return torch.stack(outs), torch.stack(valids)


class Samples(NamedTuple):
    """The views seen along ``P`` directions: ``value (V, P)`` (view quantity), ``cos (V, P)`` (cosine to the view
    axis), ``weight (V, P)`` (tent to the view border), ``valid (V, P)``."""

    value: Tensor
    cos: Tensor
    weight: Tensor
    valid: Tensor


def sample_views(preds: Tensor, views: Sequence[View], directions: Tensor, masks: Tensor | None = None) -> Samples:
    """Sample every view's map ``preds (V, 1, S, S)`` along unit ``directions (P, 3)`` of the input frame."""
    V = len(views)
    if preds.dim() != 4 or preds.shape[0] != V or preds.shape[1] != 1:
        raise ValueError(f"view predictions must be (V={V}, 1, S, S), got {tuple(preds.shape)}")
    dtype = preds.dtype
    vals, coss, wts, oks = [], [], [], []
    for k, view in enumerate(views):
        cam = view.camera
        local = directions @ view.rotation.to(directions)            # (P, 3) = (R^T d)^T
        cos = local[:, 2]
        uv, ok = cam.project(local)
        pred = preds[k:k + 1]
        if masks is not None:
            pred = torch.where(masks[k:k + 1], pred, torch.full_like(pred, math.nan))
        grid = WarpGrid(uv.unsqueeze(0).unsqueeze(0).to(dtype), ok.unsqueeze(0).unsqueeze(0), cam.width, cam.height,
                        False)
        v, has = sample_grid(pred, grid, "masked", invalid=math.nan)
        v, has = v[0, 0, 0], has[0, 0, 0] & ok
        a = ((uv[:, 0] - cam.cx) / (cam.width / 2)).abs()
        b = ((uv[:, 1] - cam.cy) / (cam.height / 2)).abs()
        w = (1.0 - torch.maximum(a, b)).clamp_min(0.0)
        has = has & torch.isfinite(v) & (w > 0) & (cos > 0)
        vals.append(torch.where(has, v, torch.zeros_like(v)))
        coss.append(cos.to(dtype))
        wts.append(torch.where(has, w, torch.zeros_like(w)).to(dtype))
        oks.append(has)
    return Samples(torch.stack(vals), torch.stack(coss), torch.stack(wts), torch.stack(oks))


@dataclass(frozen=True)
class Alignment:
    """Per-view ``scale (V,)`` and ``shift (V,)`` (``value' = scale * value + shift``), the kind and the mode."""

    scale: Tensor
    shift: Tensor
    kind: str
    mode: str
    residual: float          # robust std of the final residuals (log range or inverse range)
    points: int              # overlap pixels used


def _quantity(s: Samples, kind: str) -> Tensor:
    """Log range (``depth``) or the raw view value (``disparity``) per sample."""
    if kind == "depth":
        safe = torch.where(s.valid & (s.value > 0), s.value / s.cos.clamp_min(1e-6), torch.ones_like(s.value))
        return safe.log()
    return s.value


def align_views(s: Samples, kind: str = "depth", mode: str = "scale", robust_iters: int = 2,
                max_points: int = 60000) -> Alignment:
    """Per-view scale (and shift) from the overlaps of the samples ``s`` (module doc, step 4)."""
    if kind not in KINDS or mode not in ALIGNS:
        raise ValueError(f"align_views: kind must be one of {KINDS} and mode one of {ALIGNS}, got {kind!r}, {mode!r}")
    V = s.value.shape[0]
    dtype = torch.float64
    if mode == "none":
        return Alignment(torch.ones(V, dtype=dtype), torch.zeros(V, dtype=dtype), kind, mode, 0.0, 0)
    if kind == "depth" and mode == "affine":
        raise ValueError("align_views: affine alignment is for kind='disparity' (an affine-invariant inverse depth)")
    valid = s.valid & (s.value > 0) if kind == "depth" else s.valid
    if kind == "depth":
        valid = valid & torch.isfinite(_quantity(s, kind))
    multi = valid.sum(0) >= 2
    idx = multi.nonzero()[:, 0]
    if idx.numel() > max_points:
        idx = idx[torch.linspace(0, idx.numel() - 1, max_points).long()]
    m = valid[:, idx].to(dtype)                                     # (V, P)
    q = _quantity(s, kind)[:, idx].to(dtype)
    c = s.cos[:, idx].to(dtype)
    seen = m.sum(1) > 0
    if idx.numel() == 0 or int(seen.sum()) < 2:
        raise ValueError("align_views: the views do not overlap on any pixel the camera sees; widen the views' fov")
    scale = torch.ones(V, dtype=dtype)
    shift = torch.zeros(V, dtype=dtype)
    resid_std = 0.0
    for it in range(robust_iters + 1):
        n = m.sum(0).clamp_min(1)
        if mode == "scale":
            # unknown a_k = log s_k; residual a_k + q_kp - mean_j (a_j + q_jp) over the views j seeing p
            M = torch.diag(m.sum(1)) - (m / n) @ m.T
            mean_q = (m * q).sum(0) / n
            rhs = -(m * (q - mean_q)).sum(1)
            M = M + torch.outer(seen.to(dtype), seen.to(dtype)) / V + torch.diag((~seen).to(dtype))
            a = torch.linalg.solve(M, rhs)
            a = torch.where(seen, a - a[seen].mean(), torch.zeros_like(a))
            scale, shift = a.exp(), torch.zeros_like(a)
            r = m * (a[:, None] + q)
            res = r - (r.sum(0) / n)
        else:
            # unknown (s_k, t_k); residual cos_k (s_k D_k + t_k) - mean_j cos_j (s_j D_j + t_j)
            u, w = m * c * q, m * c
            Z = torch.cat([u, w], 0)                                 # (2V, P)
            M = torch.zeros(2 * V, 2 * V, dtype=dtype)
            ii = torch.arange(V)
            M[ii, ii] = (u * u).sum(1)
            M[ii, ii + V] = M[ii + V, ii] = (u * w).sum(1)
            M[ii + V, ii + V] = (w * w).sum(1)
            M = M - (Z / n) @ Z.T
            keep = torch.cat([seen, seen])
            evals, evecs = torch.linalg.eigh(M[keep][:, keep])
            theta = torch.zeros(2 * V, dtype=dtype)
            theta[keep] = evecs[:, 0]
            sv = theta[:V]
            mean_s = sv[seen].mean()
            if float(mean_s.abs()) < 1e-12:
                raise ValueError("align_views: degenerate affine alignment (overlaps too small)")
            theta = theta / mean_s
            scale = torch.where(seen, theta[:V], torch.ones(V, dtype=dtype))
            shift = torch.where(seen, theta[V:], torch.zeros(V, dtype=dtype))
            r = m * c * (scale[:, None] * q + shift[:, None])
            res = (r - r.sum(0) / n) / (r.sum(0) / n).abs().clamp_min(1e-12)
        used = res[m > 0]
        mad = (used - used.median()).abs().median() * 1.4826 if used.numel() else torch.zeros((), dtype=dtype)
        resid_std = float(mad)
        if it < robust_iters and used.numel():
            # 3 robust std, never below 2 %: nearly exact views keep every overlap (a tiny threshold would cut the
            # overlap graph into pieces whose relative scale is then unknown)
            out = (res.abs() > (3 * mad).clamp_min(0.02)) & (m > 0)
            if not bool(out.any()):
                break
            m = m * (~out).to(dtype)
            seen = m.sum(1) > 0
    return Alignment(scale, shift, kind, mode, resid_std, int(idx.numel()))


class FusedViews:
    """The aligned views as one function of direction: :meth:`range` ``(P, 3) -> (range (P,), valid (P,))``."""

    def __init__(self, preds: Tensor, views: Sequence[View], alignment: Alignment, masks: Tensor | None = None) -> None:
        self.preds, self.views, self.alignment, self.masks = preds, list(views), alignment, masks

    def samples(self, directions: Tensor) -> Samples:
        return sample_views(self.preds, self.views, directions, self.masks)

    def range(self, directions: Tensor) -> tuple[Tensor, Tensor]:
        """Fused range from the centre along unit ``directions (P, 3)``: ``(range (P,), valid (P,))``."""
        s = self.samples(directions)
        al = self.alignment
        sc = al.scale.to(s.value)[:, None]
        sh = al.shift.to(s.value)[:, None]
        w = s.weight
        if al.kind == "depth":
            ok = s.valid & (s.value > 0)
            logr = torch.where(ok, torch.log(torch.where(ok, sc * s.value / s.cos.clamp_min(1e-6),
                                                         torch.ones_like(s.value))), torch.zeros_like(s.value))
            w = torch.where(ok, w, torch.zeros_like(w))
            den = w.sum(0)
            has = den > 0
            r = torch.exp((w * logr).sum(0) / torch.where(has, den, torch.ones_like(den)))
        else:
            inv = s.cos * (sc * s.value + sh)                     # inverse range per view
            ok = s.valid
            w = torch.where(ok, w, torch.zeros_like(w))
            den = w.sum(0)
            has = den > 0
            inv_f = (w * torch.where(ok, inv, torch.zeros_like(inv))).sum(0) / torch.where(has, den, torch.ones_like(den))
            has = has & (inv_f > 0)
            r = 1.0 / torch.where(has, inv_f, torch.ones_like(inv_f))
        return torch.where(has, r, torch.zeros_like(r)), has

    def border_band(self, directions: Tensor, width: float = 0.1) -> Tensor:
        """``(P,)`` bool: the direction lies within ``width`` (fraction of the half side) of some view's border while
        inside that view — where a view's weight falls to 0, i.e. where seams would show."""
        s = self.samples(directions)
        return ((s.weight > 0) & (s.weight < width) & s.valid).any(0)


class ViewDepth(NamedTuple):
    """Result of :func:`depth_through_views`: ``depth (1, H, W)`` range along each pixel's ray (0 where invalid),
    ``valid (1, H, W)``, the views, their predictions ``(V, 1, S, S)``, the alignment, ``border (1, H, W)`` (pixels
    in a view-border band, for seam statistics) and the views' cut masks ``(V, 1, S, S)`` (where the camera sees
    each view pixel)."""

    depth: Tensor
    valid: Tensor
    views: list
    preds: Tensor
    alignment: Alignment
    border: Tensor
    masks: Tensor | None = None


#: a non-central pixel's fixed point counts as converged when its last step moved ``t`` by at most this fraction
NONCENTRAL_TOL = 1e-3


def fuse_on_camera(fused: FusedViews, camera: Camera, noncentral_iters: int = 8,
                   assumed_range: float = 3.0) -> tuple[Tensor, Tensor, Tensor]:
    """The fused range on every pixel of ``camera``: ``(depth (1, H, W), valid (1, H, W), border (1, H, W))``.

    A non-central pixel's ray ``o + t d`` starts at the fused range along ``d`` from the centre, or, where no view
    has a value there (the pole rows of a non-central panorama look along directions that are inside the rig at
    ``assumed_range``: their own direction is not cut, the directions of the points they see are), at the ``t``
    with ``|o + t d| = assumed_range``; then ``noncentral_iters`` fixed-point steps ``t <- the root of
    |o + t d| = r(dir(o + t d))``. A pixel is valid when the last step had a fused range and moved ``t`` by at most
    :data:`NONCENTRAL_TOL` (relative): a fixed point that did not settle (an oscillation across a depth edge) is
    left out, never reported."""
    dtype = fused.preds.dtype if fused.preds.dtype == torch.float64 else torch.float32
    o, d, ok = _input_rays(camera, torch.float64, fused.preds.device)
    H, W = camera.height, camera.width
    o, d, ok = o.reshape(-1, 3), d.reshape(-1, 3), ok.reshape(-1)
    r, has = fused.range(d.to(dtype))
    t = r.to(torch.float64)
    if not camera.central:
        od = (o * d).sum(-1)
        oo = (o * o).sum(-1)
        start = -od + torch.sqrt((od * od - oo + float(assumed_range) ** 2).clamp_min(0))
        t = torch.where(has & (t > 0), t, start)
        for _ in range(max(1, int(noncentral_iters))):
            X = o + t[:, None] * d
            dirs = X / X.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            r, has2 = fused.range(dirs.to(dtype))
            r = r.to(torch.float64)
            disc = od * od - oo + r * r
            good = has2 & (disc >= 0)
            t_new = -od + torch.sqrt(disc.clamp_min(0))
            step = (t_new - t).abs()
            t = torch.where(good, t_new, t)
            has = good
        has = has & (step <= NONCENTRAL_TOL * t.abs())
    valid = ok & has & (t > 0) & torch.isfinite(t)
    depth = torch.where(valid, t, torch.zeros_like(t)).to(dtype)
    border = fused.border_band(d.to(dtype)) & valid
    return depth.reshape(1, H, W), valid.reshape(1, H, W), border.reshape(1, H, W)


def visible_views(camera: Camera, views: Sequence[View], min_fraction: float = 0.001) -> list[View]:
    """The views of which the camera sees more than ``min_fraction`` of the pixels (a 195° fisheye sees none of the
    views looking backwards)."""
    dummy = torch.zeros(1, camera.height, camera.width)
    _, masks = cut_views(dummy, camera, views)
    return [v for v, m in zip(views, masks) if float(m.float().mean()) > min_fraction]


def depth_through_views(image: Tensor, camera: Camera, predict: Callable[[Tensor, list], Tensor], layout: str = "tangent",
                        size: int = 518, fov: float | None = None, kind: str = "depth", align: str = "scale",
                        assumed_range: float = 3.0, batch: int = 4, views: Sequence[View] | None = None,
                        robust_iters: int = 2, noncentral_iters: int = 8) -> ViewDepth:
    """Depth of ``image (3, H, W)`` from ``camera`` through a perspective model ``predict`` (module doc).

    Args:
        predict: ``predict(images (n, 3, S, S) RGB in [0, 1], views (the n View objects))`` -> ``(n, 1, S, S)``
            z-depth (``kind="depth"``) or inverse depth (``kind="disparity"``); called with at most ``batch`` views
            at a time, in view order (a network ignores ``views``; a test stand-in renders them).
        layout, size, fov: the views (:func:`view_layout`); ``views`` overrides them.
        align: ``"scale"`` (metric or scale-ambiguous depth), ``"affine"`` (affine-invariant inverse depth), or
            ``"none"``.
        assumed_range: metres at which a non-central camera is sampled for the views (:func:`cut_views`).
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if align not in ALIGNS:
        raise ValueError(f"align must be one of {ALIGNS}, got {align!r}")
    views = list(views) if views is not None else view_layout(layout, size, fov)
    imgs, masks = cut_views(image, camera, views, assumed_range)
    if camera.central:
        seen = masks.flatten(1).float().mean(1) > 0.001
    else:  # which views the camera sees does not depend on the range assumed for the cut
        seen = cut_views(torch.zeros(1, camera.height, camera.width), camera, views, 1e3)[1].flatten(1).float().mean(1) > 0.001
    keep = [i for i in range(len(views)) if bool(seen[i])]
    views = [views[i] for i in keep]
    imgs, masks = imgs[keep], masks[keep]
    preds = []
    for i in range(0, len(views), max(1, int(batch))):
        p = predict(imgs[i:i + batch], views[i:i + batch])
        if p.dim() == 3:
            p = p.unsqueeze(1)
        if p.shape != (imgs[i:i + batch].shape[0], 1, *imgs.shape[-2:]):
            raise ValueError(f"predict returned {tuple(p.shape)} for views of shape {tuple(imgs[i:i + batch].shape)}; "
                             "expected (n, 1, S, S)")
        preds.append(p.detach())
    pred = torch.cat(preds)
    if not torch.isfinite(pred).all():
        raise ValueError("predict returned non-finite values")
    s = sample_views(pred, views, _input_rays(camera, pred.dtype, pred.device)[1].reshape(-1, 3), masks)
    alignment = align_views(s, kind, align, robust_iters)
    fused = FusedViews(pred, views, alignment, masks)
    depth, valid, border = fuse_on_camera(fused, camera, noncentral_iters, assumed_range)
    return ViewDepth(depth, valid, views, pred, alignment, border, masks)


def fuse_maps(maps: Tensor, views: Sequence[View], directions: Tensor, masks: Tensor | None = None
              ) -> tuple[Tensor, Tensor]:
    """Per-view maps ``(V, C, S, S)`` (e.g. class probabilities) along unit ``directions (P, 3)``: the tent-weighted
    mean over the views that see each direction (as :class:`FusedViews` fuses the range, no alignment) ->
    ``(values (C, P), valid (P,))``."""
    out, den = [], None
    for c in range(maps.shape[1]):
        s = sample_views(maps[:, c:c + 1], views, directions, masks)
        den = s.weight.sum(0)
        out.append((s.weight * s.value).sum(0) / den.clamp_min(1e-12))
    return torch.stack(out), den > 0


class ThroughViews(torch.nn.Module):
    """A perspective depth network run on whole images of ``camera``, always through the view chain.

    ``forward(x (B, 3, H, W))``, ``x`` images of ``camera`` (or of the camera uniformly resized to ``W x H``): every
    image is cut into the views, ``net`` predicts each view's z-depth (and class logits), and the views are aligned
    and fused on the camera's pixels by :func:`depth_through_views` -> ``{"depth": (B, 1, H, W)`` float32 range along
    each pixel's ray (0 where no view gives a value), ``"semantic": (B, C, H, W)`` log of the fused class
    probabilities (when ``net`` returns ``"semantic"`` logits ``(n, C, S, S)``; uniform where no view sees the
    pixel)``}``. The network's ``"depth"`` must be the views' z-depth in metres (``align="scale"`` keeps its metric
    scale, ``"none"`` trusts every view as it is).

    The same computation in every mode: there is no other route (no branch on the input's size, on
    ``training``, on grad mode). The chain is **not differentiable**: ``net`` always runs under ``torch.no_grad()``
    and with autocast off (float32), in train and eval mode alike, so the outputs carry no gradient. ``net`` keeps
    its own ``train()``/``eval()`` mode (dropout and batch norm behave as they do in that mode; evaluate.py runs
    ``eval()``). To train the network, train it on the views themselves (:class:`omnidl.data.views.PanoramaViews`).

    Args:
        net: the perspective network: ``net(images (n, 3, S, S))["depth"]`` ``(n, 1, S, S)`` z-depth in metres.
        camera: the camera of the whole images (a ``Camera`` or a config mapping; no files are read).
        layout, size, fov: the views (:func:`view_layout`; the training views' own).
        align, assumed_range, noncentral_iters, batch: as :func:`depth_through_views` (``batch`` views per call
            of ``net``).
    """

    def __init__(self, net: torch.nn.Module, camera, layout: str = "tangent", size: int = 518,
                 fov: float | None = None, align: str = "scale", assumed_range: float = 3.0,
                 noncentral_iters: int = 8, batch: int = 16) -> None:
        super().__init__()
        if align not in ("scale", "none"):
            raise ValueError(f"ThroughViews: align must be 'scale' or 'none' (a z-depth network), got {align!r}")
        if int(batch) < 1:
            raise ValueError(f"ThroughViews: batch must be >= 1 views per call of the network, got {batch}")
        self.net = net
        self.camera = resolve_camera(camera, allow_files=False)
        self.layout, self.size, self.fov = layout, int(size), fov
        self.views = view_layout(layout, self.size, fov)
        self.align, self.assumed_range = align, float(assumed_range)
        self.noncentral_iters, self.batch = int(noncentral_iters), int(batch)
        self._cameras: dict[tuple[int, int], tuple[Camera, list[View]]] = {}

    def extra_repr(self) -> str:
        return (f"camera={type(self.camera).__name__}({self.camera.width}x{self.camera.height}), "
                f"layout={self.layout!r}, size={self.size}, views={len(self.views)}, align={self.align!r}")

    def whole_camera(self, width: int, height: int) -> tuple[Camera, list[View]]:
        """The camera at ``width x height`` (a uniform resize of :attr:`camera`, else a ``ValueError``) and the
        views it sees (cached)."""
        key = (int(width), int(height))
        if key not in self._cameras:
            cam = resolve_camera(self.camera, key[0], key[1], check_aspect=True)
            self._cameras[key] = (cam, visible_views(cam, self.views))
        return self._cameras[key]

    def forward(self, x: Tensor) -> dict[str, Tensor]:
        if x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"ThroughViews: input must be images (B, 3, H, W) of the camera, got {tuple(x.shape)}")
        H, W = x.shape[-2:]
        cam, views = self.whole_camera(W, H)
        depths, sems = [], []
        with torch.no_grad(), torch.autocast(device_type=x.device.type, enabled=False):
            for b in range(x.shape[0]):
                logits: list[Tensor] = []

                def predict(images: Tensor, _views: list, logits: list[Tensor] = logits) -> Tensor:
                    out = self.net(images.to(x.device))
                    if "semantic" in out:
                        logits.append(out["semantic"].float())
                    return out["depth"].float()

                res = depth_through_views(x[b].float(), cam, predict, views=views, kind="depth", align=self.align,
                                          assumed_range=self.assumed_range, batch=self.batch,
                                          noncentral_iters=self.noncentral_iters)
                depths.append(res.depth)
                if logits:
                    sems.append(self._semantic(torch.cat(logits), res, cam))
        out = {"depth": torch.stack(depths).float()}
        if sems:
            out["semantic"] = torch.stack(sems)
        return out

    def _semantic(self, logits: Tensor, res: ViewDepth, cam: Camera) -> Tensor:
        """``(C, H, W)`` log of the views' class probabilities fused along each pixel's ray (non-central: towards
        the point at the fused depth)."""
        rays = cam.unproject_grid(dtype=torch.float64, device=logits.device)
        o, d = rays.origin.reshape(-1, 3), rays.direction.reshape(-1, 3)
        if not cam.central:
            t = res.depth.reshape(-1).to(torch.float64)
            X = o + t[:, None] * d
            d = torch.where(res.valid.reshape(-1, 1), X / X.norm(dim=-1, keepdim=True).clamp_min(1e-12), d)
        probs, ok = fuse_maps(logits.softmax(1), res.views, d.to(logits.dtype), res.masks)
        C = logits.shape[1]
        probs = torch.where(ok[None], probs, torch.full_like(probs, 1.0 / C))
        return probs.clamp_min(1e-8).log().reshape(C, cam.height, cam.width)


__all__ = ["View", "view_layout", "view_grid", "view_warp", "view_cos", "cut_views", "sample_views", "Samples", "align_views",
           "Alignment", "FusedViews", "fuse_on_camera", "depth_through_views", "visible_views", "ViewDepth", "LAYOUTS",
           "KINDS", "ALIGNS", "NONCENTRAL_TOL", "fuse_maps", "ThroughViews"]
