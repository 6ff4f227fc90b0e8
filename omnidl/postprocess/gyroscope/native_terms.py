"""The photometric gyroscopes' iterations in one native call each (``omnidl/nn/csrc/sphere_terms.c``).

A Gauss-Newton iteration of PVG or MPP is ~15-35 small tensor ops over 10k (PVG) or 2.6k (MPP, 4 starts)
points; on a 2-core machine each op costs 10-25 us of dispatch and memory passes, so an iteration took
0.4-2 ms. Here one pass per iteration reads the image at every point and sums the normal equations:

* :func:`pvg_normal_equations` -- ``[u; e][u; e]^T`` summed over the vertices, the product that
  :class:`~omnidl.postprocess.gyroscope.pvg.PVGTerms` feeds to ``torch.bmm`` (same points, tangent basis,
  five reads and central differences);
* :func:`pvg_stage` -- a whole blur stage of PVG on all three axes: those sums, the damped 3x3 solve, the
  trust region and the Rodrigues update of ``R`` per iteration;
* :func:`mpp_yaw_loop` -- the whole yaw loop of ``_mpp_fast`` (points and Jacobian directions from the
  three basis terms, four-channel table reads, ``J.J``, ``J.e``, ``e.e``, the step, the best angle per start).

Reads (:func:`sphere_read`) are :meth:`SphereImage.read_grid`'s (``grid_sample`` of the wrapped image) with a
polynomial ``atan2`` (within a few float32 ulps of PyTorch's); sums in double. They run for float32 CPU tensors
with the native library built (:mod:`omnidl.nn.native`), not while a graph is captured; elsewhere (float64, CUDA,
``OMNIDL_NATIVE=0``) the solvers keep their tensor ops. Results equal those ops' to float32 rounding
(``tests/postprocess/gyroscope/test_native_terms.py``).
"""
from __future__ import annotations

import torch
from torch import Tensor

from omnidl.nn import native
from omnidl.nn.capture import capturing

#: ``False``: always the tensor ops (benchmarks' in-process A/B, tests)
ENABLED = True


def applies(*tensors: Tensor) -> bool:
    """Whether the native iterations run for these tensors (float32 on the CPU, library built, not capturing)."""
    return ENABLED and not capturing() and native.accepts(*tensors)


def _check(where: str, **tensors: Tensor) -> None:
    """The kernels read float32 CPU memory: anything else is an error that names the operand."""
    for name, t in tensors.items():
        if t.device.type != "cpu" or t.dtype != torch.float32:
            raise ValueError(f"{where}: {name} must be a float32 CPU tensor, got {t.dtype} on {t.device}")


def _rows(t: Tensor, B: int, n: int, name: str) -> tuple[Tensor, int]:
    """``t (B|1, n)`` as contiguous rows and their stride (0 for one row shared by all ``B``)."""
    if t.dim() != 2 or t.shape[-1] != n or t.shape[0] not in (1, B):
        raise ValueError(f"{name} must have shape ({B} or 1, {n}), got {tuple(t.shape)}")
    t = t.contiguous()
    return t, (0 if t.shape[0] == 1 else n)


def sphere_read(image: Tensor, directions: Tensor) -> Tensor:
    """Values ``(C, M)`` of ``image (C, H, W)`` equirect at ``directions (M, 3)`` (any positive length), as
    :meth:`SphereImage.read` reads them (the native kernels' read; NaN for a non-finite direction)."""
    if image.dim() != 3 or directions.dim() != 2 or directions.shape[-1] != 3:
        raise ValueError(f"sphere_read: expected image (C, H, W) and directions (M, 3), got {tuple(image.shape)} "
                         f"and {tuple(directions.shape)}")
    _check("sphere_read", image=image, directions=directions)
    img = image.contiguous()
    C, H, W = img.shape
    x, y, z = (d.contiguous() for d in directions.unbind(-1))
    out = torch.empty(C, directions.shape[0], dtype=torch.float32)
    native.library().omnidl_sphere_read(img.data_ptr(), H * W, C, H, W, x.data_ptr(), y.data_ptr(), z.data_ptr(),
                                        directions.shape[0], out.data_ptr(), max(1, torch.get_num_threads()))
    return out


def _pvg_operands(image: Tensor, X: Tensor, I_ref: Tensor) -> tuple[Tensor, Tensor, Tensor, int]:
    """``image (B, 1, H, W)``, ``X (N, 3)`` and ``I_ref (B|1, N)`` as contiguous operands, and ``I_ref``'s row
    stride."""
    if image.dim() != 4 or image.shape[1] != 1:
        raise ValueError(f"PVG: image must have shape (B, 1, H, W), got {tuple(image.shape)}")
    if X.dim() != 2 or X.shape[1] != 3:
        raise ValueError(f"PVG: vertices must have shape (N, 3), got {tuple(X.shape)}")
    _check("PVG", image=image, vertices=X, I_ref=I_ref)
    ref, ref_stride = _rows(I_ref, image.shape[0], X.shape[0], "I_ref")
    return image.contiguous(), X.contiguous(), ref, ref_stride


def pvg_normal_equations(image: Tensor, R: Tensor, X: Tensor, I_ref: Tensor, h: float) -> Tensor:
    """``Q (B, 4, 4)`` float64: ``sum_i [u_i; e_i][u_i; e_i]^T`` of :class:`~omnidl.postprocess.gyroscope.pvg.PVGTerms`
    (``u = grad x p``, ``e = I_cur(p) - I_ref`` at ``p = R^T X_i``) for ``image (B, 1, H, W)`` equirect,
    ``R (B, 3, 3)``, ``X (N, 3)``, ``I_ref (B|1, N)``; ``h``: the central differences' step (radians)."""
    img, Xc, ref, ref_stride = _pvg_operands(image, X, I_ref)
    B, _, H, W = img.shape
    _check("PVG", R=R)
    Rc = R.expand(B, 3, 3).contiguous()
    Q = torch.empty(B, 4, 4, dtype=torch.float64)
    native.library().omnidl_pvg_terms(img.data_ptr(), H * W, H, W, Rc.data_ptr(), Xc.data_ptr(), Xc.shape[0],
                                      ref.data_ptr(), ref_stride, B, float(h), Q.data_ptr(),
                                      max(1, torch.get_num_threads()))
    return Q


def pvg_stage(image: Tensor, R: Tensor, X: Tensor, I_ref: Tensor, h: float, max_iter: int,
              tol: float) -> tuple[Tensor, Tensor, int]:
    """One blur stage of ``_pvg_fast`` on all three axes from ``R (B, 3, 3)`` (arguments as
    :func:`pvg_normal_equations`): returns the refined ``R`` (a new tensor), the last iteration's sums ``Q (B, 4, 4)``
    float64 and the number of iterations run."""
    img, Xc, ref, ref_stride = _pvg_operands(image, X, I_ref)
    B, _, H, W = img.shape
    _check("PVG", R=R)
    Rc = R.expand(B, 3, 3).contiguous().clone()
    Q = torch.zeros(B, 4, 4, dtype=torch.float64)
    it = native.library().omnidl_pvg_stage(img.data_ptr(), H * W, H, W, Rc.data_ptr(), Xc.data_ptr(), Xc.shape[0],
                                           ref.data_ptr(), ref_stride, B, float(h), int(max_iter), float(tol),
                                           Q.data_ptr(), max(1, torch.get_num_threads()))
    if it < 0:
        raise ValueError("PVG: singular normal equations (the image has no gradient at the vertices?)")
    return Rc, Q, it


def mpp_yaw_loop(table: Tensor, basis: Tensor, G_ref: Tensor, theta: Tensor, max_iter: int,
                 tol: float) -> tuple[Tensor, Tensor, int]:
    """MPP's yaw iterations: ``table (B, 4, h, 2h)`` (``G`` and its gradient, :func:`mpp_table_fast`), ``basis
    (B, 3, 6M)`` (``_mpp_fast``'s three terms of the points and Jacobian directions), ``G_ref (B|1, M)``,
    ``theta (B, T)`` the starts. Returns the angle of least cost per start ``(B, T)``, that cost ``(B, T)`` and the
    number of iterations run."""
    B, T = theta.shape
    M = basis.shape[-1] // 6
    if table.dim() != 4 or table.shape[:2] != (B, 4) or table.shape[-1] != 2 * table.shape[-2]:
        raise ValueError(f"mpp_yaw_loop: table must have shape ({B}, 4, h, 2h), got {tuple(table.shape)}")
    if basis.shape != (B, 3, 6 * M):
        raise ValueError(f"mpp_yaw_loop: basis must have shape ({B}, 3, 6M), got {tuple(basis.shape)}")
    _check("mpp_yaw_loop", table=table, basis=basis, G_ref=G_ref, theta=theta)
    tab, bas = table.contiguous(), basis.contiguous()
    ref, ref_stride = _rows(G_ref, B, M, "G_ref")
    best = theta.contiguous().clone()
    cost = torch.empty(B, T, dtype=torch.float32)
    h = table.shape[-2]
    it = native.library().omnidl_mpp_yaw(tab.data_ptr(), 4 * h * 2 * h, h, bas.data_ptr(), M, ref.data_ptr(),
                                         ref_stride, B, T, int(max_iter), float(tol), best.data_ptr(),
                                         cost.data_ptr())
    if it < 0:
        raise MemoryError("mpp_yaw_loop: the native loop could not allocate its buffer")
    return best, cost, it


__all__ = ["ENABLED", "applies", "mpp_yaw_loop", "pvg_normal_equations", "pvg_stage", "sphere_read"]
