"""PVG, the photometric visual gyroscope (André & Caron 2022; thesis §6.2.3): 3-DoF rotation refinement.

Raw grey levels (no normalisation) of the reference at the vertices ``X_i`` of an icosahedron subdivided
``n`` times (default 5, 10242 vertices) are compared with the current image read at ``p_i = R.T X_i``:

    C(R) = sum_i (I_cur(R.T X_i) - I_ref(X_i))^2

Gauss-Newton on the three rotation angles, ``R <- exp([w]x) R``, with the analytic Jacobian
``(R grad I_cur(p_i)) x X_i``. The spherical image gradient ``grad I_cur(p)`` is taken in the image
(bilinear reads of the equirectangular image at ``p`` moved by +-h along two tangent directions,
``h`` = one pixel of latitude), so it has no singularity at the poles. The convergence domain is narrow
(~±12.5° in the thesis): start from HoLiNet + MPP. A coarse-to-fine schedule of Gaussian blurs
(``blur_px``) widens it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from .icosahedron import icosahedron_vertices
from .photometric import SphereImage, blur_fast, damped_step, rodrigues, to_gray


class PVGTerms:
    """The per-iteration terms of PVG for ``B`` rotations of the vertices ``X (N, 3)``, in buffers allocated once.

    ``terms(image, R, I_ref)`` -> ``(B, 4, N)``: the rows ``u = grad x p`` (3) and the residual
    ``I_cur(p) - I_ref`` (1) at the points ``p = R.T X`` (kept as component rows ``(B, 3, N)``). The spherical
    gradient from five reads: ``p`` and ``p +- h t1``, ``p +- h t2`` with the tangent basis
    ``t1 = a x p / |a x p|`` (``a = e_x`` where ``|p_x| < 0.9``, else ``e_y``), ``t2 = p x t1``, central
    differences over ``2 atan(h)``; so with ``grad = g1 t1 + g2 t2``: ``grad x p = g2 t1 - g1 t2``. The Jacobian of
    :func:`pvg_refine` is then ``(R grad) x X = R (grad x p)`` (``X = R p``): rows ``R u``, and
    ``J^T J = R (U U^T) R^T``, ``J^T e = R U e`` come from one ``(4, N) x (N, 4)`` product of the output.
    The output is overwritten by the next call.
    """

    def __init__(self, X: Tensor, B: int) -> None:
        dtype, dev, N = X.dtype, X.device, X.shape[0]
        self.N = N
        self.Xt = X.T.contiguous().expand(B, 3, N)
        self.P = torch.empty(B, 3, N, dtype=dtype, device=dev)
        self.t1 = torch.empty(B, 3, N, dtype=dtype, device=dev)
        self.t2 = torch.empty(B, 3, N, dtype=dtype, device=dev)
        self.pts = torch.empty(B, 3, 5, N, dtype=dtype, device=dev)  # p, p + h t1, p - h t1, p + h t2, p - h t2
        self.out = torch.empty(B, 4, N, dtype=dtype, device=dev)
        self._p = self.P.unbind(1)
        self._t1 = self.t1.unbind(1)
        self._t2 = self.t2.unbind(1)
        self._pts = self.pts.unbind(2)
        self._xyz = self.pts.view(B, 3, 5 * N).unbind(1)
        self._u, self._e = self.out[:, :3], self.out[:, 3]
        self._zero = torch.zeros((), dtype=dtype, device=dev)

    def __call__(self, image: SphereImage, R: Tensor, I_ref: Tensor, h: float | None = None) -> Tensor:
        h = math.pi / image.H if h is None else h
        B, N = self.P.shape[0], self.N
        P, t1, t2 = self.P, self.t1, self.t2
        px, py, pz = self._p
        a1, a2, a3 = self._t1
        b1, b2, b3 = self._t2
        torch.bmm(R.transpose(-1, -2), self.Xt, out=P)  # rows of R.T X
        use_x = px.abs() < 0.9  # a = e_x: a x p = (0, -pz, py); a = e_y: a x p = (pz, 0, -px)
        torch.where(use_x, self._zero, pz, out=a1)
        torch.where(use_x, pz, self._zero, out=a2).neg_()
        torch.where(use_x, py, px.neg(), out=a3)
        sel = torch.where(use_x, py, px)
        nrm = torch.addcmul(pz * pz, sel, sel).sqrt_().clamp_min_(1e-12)  # |a x p|
        t1.div_(nrm.unsqueeze(1))
        torch.mul(py, a3, out=b1).addcmul_(pz, a2, value=-1.0)  # t2 = p x t1
        torch.mul(pz, a1, out=b2).addcmul_(px, a3, value=-1.0)
        torch.mul(px, a2, out=b3).addcmul_(py, a1, value=-1.0)
        q0, q1, q2, q3, q4 = self._pts
        q0.copy_(P)
        torch.add(P, t1, alpha=h, out=q1)
        torch.add(P, t1, alpha=-h, out=q2)
        torch.add(P, t2, alpha=h, out=q3)
        torch.add(P, t2, alpha=-h, out=q4)
        v = image.read_grid(*self._xyz).view(B, 5, N)
        g = (v[:, 1::2] - v[:, 2::2]).div_(2 * math.atan(h))  # (B, 2, N): g1, g2 (central differences)
        torch.mul(t1, g[:, 1:], out=self._u).addcmul_(t2, g[:, :1], value=-1.0)
        torch.sub(v[:, 0], I_ref, out=self._e)
        return self.out


def pvg_reference_values(reference: Tensor, level: int = 5, blur_px: Sequence[float] = (4.0, 1.5, 0.5)) -> Tensor:
    """``(S, B, N)`` grey levels of ``reference (B, 3|1, H, W)`` at the level-``level`` vertices after each of
    the ``S`` blurs: what :func:`pvg_refine` compares with, to prepare once per reference
    (``reference_values=``)."""
    dtype = reference.dtype if reference.dtype == torch.float64 else torch.float32
    ref = to_gray(reference.to(dtype))
    X = icosahedron_vertices(level, dtype, ref.device)
    Xt = X.T.unsqueeze(0)
    return torch.stack([SphereImage(blur_fast(ref, s)).read_xyz(*Xt.unbind(1))[:, 0] for s in blur_px])


@dataclass
class PVGResult:
    rotation: Tensor  # (B, 3, 3) refined R_ref_cur
    cost: Tensor      # (B,) final mean squared residual
    iterations: int


def pvg_refine(current: Tensor, reference: Tensor, R_init: Tensor | None = None, level: int = 5,
               max_iter: int = 30, tol: float = 1e-6, blur_px: Sequence[float] = (4.0, 1.5, 0.5),
               dofs: Sequence[bool] = (True, True, True), reference_values: Tensor | None = None) -> PVGResult:
    """Refine ``R_ref_cur`` so that ``current`` read at ``R.T X`` matches ``reference`` at ``X``.

    Per blur stage both images are blurred (:func:`blur_fast`), the current one prepared once for reads
    (:class:`SphereImage`), and each Gauss-Newton iteration takes the points and Jacobian rows as ``(B, 3, N)``
    component rows in buffers allocated once, ``J^T J`` and ``J^T e`` from one small product (:class:`PVGTerms`).

    Args:
        current, reference: ``(B, 3|1, H, W)`` equirect images (``reference`` may have batch 1).
        R_init: ``(B, 3, 3)`` start (identity default). ``level``: icosahedron subdivision (thesis n = 5).
        max_iter, tol: per blur stage; stop when every update is below ``tol`` rad.
        blur_px: coarse-to-fine Gaussian blurs (pixels) of both images; ``(0,)`` = raw images only.
        dofs: which rotation axes (reference frame x, y, z) are optimised.
        reference_values: ``pvg_reference_values(reference, level, blur_px)`` prepared once per reference
            (``reference`` is then not read).
    Returns:
        :class:`PVGResult`.
    """
    dtype = current.dtype if current.dtype == torch.float64 else torch.float32
    cur = to_gray(current.to(dtype))
    B = cur.shape[0]
    X = icosahedron_vertices(level, dtype, cur.device)
    R = (torch.eye(3, dtype=dtype, device=cur.device) if R_init is None else R_init.to(dtype)).expand(B, 3, 3).clone()
    if reference_values is None:
        reference_values = pvg_reference_values(reference, level, blur_px)
    elif reference_values.shape[0] != len(blur_px) or reference_values.shape[-1] != X.shape[0]:
        raise ValueError(f"pvg_refine: reference_values {tuple(reference_values.shape)} do not fit "
                         f"{len(blur_px)} blur stages x {X.shape[0]} vertices (level {level})")
    return _pvg_stages(cur, reference_values.to(dtype), X, R, tuple(bool(d) for d in dofs), max_iter, tol, blur_px)


def _pvg_stages(cur: Tensor, ref_values: Tensor, X: Tensor, R: Tensor, dofs: tuple[bool, ...], max_iter: int,
                tol: float, blur_px: Sequence[float]) -> PVGResult:
    """The Gauss-Newton loop of :func:`pvg_refine` on :class:`PVGTerms`: ``J^T J = R M R^T``, ``J^T e = R c`` with
    ``[M c; c^T e^T e] = T T^T``, ``T = PVGTerms(...)(...)``; with all three axes free the damped solve runs in the
    frame of the points (``A + l I = R (M + l I) R^T``)."""
    B, dtype, dev = cur.shape[0], cur.dtype, cur.device
    sel = [i for i, d in enumerate(dofs) if d]
    all_dofs = len(sel) == 3
    eye9 = 1e-9 * torch.eye(3, dtype=dtype, device=dev)  # damped_step's damping (all three axes)
    terms = PVGTerms(X, B)
    Q = torch.empty(B, 4, 4, dtype=dtype, device=dev)
    QT = terms.out.transpose(1, 2)
    M, c = Q[:, :3, :3], Q[:, :3, 3]
    diag = torch.diagonal(M, dim1=-2, dim2=-1)
    it_total = 0
    for s, sigma in enumerate(blur_px):
        blurred = blur_fast(cur, sigma)
        img = SphereImage(blurred)
        I_ref = ref_values[s]
        h = math.pi / blurred.shape[-2]
        for _ in range(max_iter):
            it_total += 1
            torch.bmm(terms(img, R, I_ref, h), QT, out=Q)
            if all_dofs:  # A + l I = R (M + l I) R.T (trace-invariant damping): solve in the frame of the points
                scale = diag.mean(-1, keepdim=True).clamp_min_(1e-30)
                y = torch.linalg.solve(torch.addcmul(M, scale.unsqueeze(-1), eye9), c)  # dx = -R y
                n = y.norm(dim=-1, keepdim=True)
                w = torch.bmm(R, (y * (-0.35 / n).clamp_(min=-1.0)).unsqueeze(-1))[..., 0]  # trust region: <= 20°
            else:
                A = R @ M @ R.transpose(-1, -2)
                b = (R @ c.unsqueeze(-1))[..., 0]
                w = torch.zeros(B, 3, dtype=dtype, device=dev)
                w[:, sel] = damped_step(A[:, sel][:, :, sel], b[:, sel])
                n = w.norm(dim=-1, keepdim=True)
                w = w * (0.35 / n).clamp(max=1.0)  # trust region: at most 20° per step
            R = rodrigues(w) @ R
            if bool((n < tol).all()):
                break
    cost = Q[:, 3, 3] / X.shape[0] if it_total else torch.zeros(B, dtype=dtype, device=dev)
    return PVGResult(R, cost, it_total)
