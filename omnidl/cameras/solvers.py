"""Small vectorised solvers shared by the camera models.

Every iterative inverse (Kannala–Brandt ``d(theta) = r``, OCamCalib angle, non-central
reflection point) is solved without autograd and then *polished* by one Newton step
that is differentiable: with ``x*`` the (detached) converged root of ``f(x) = y``,
``x = x* - (f(x*) - y) / f'(x*)`` has value ``x*`` (up to rounding) and gradient
``dx/dy = 1 / f'(x*)`` — the implicit-function derivative — so gradients are exact and
do not depend on the number of iterations.
"""
from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

Fn = Callable[[Tensor], Tensor]


def default_tol(dtype: torch.dtype) -> float:
    """Absolute residual tolerance used by the solvers for ``dtype``."""
    return 4 * torch.finfo(dtype).eps


@torch.no_grad()
def solve_increasing(f: Fn, df: Fn, y: Tensor, lo: Tensor, hi: Tensor, x0: Tensor | None = None,
                     max_iter: int = 100) -> Tensor:
    """Root of ``f(x) = y`` for ``f`` increasing on ``[lo, hi]`` (elementwise, broadcast).

    Safeguarded Newton: a bracket ``[lo, hi]`` is kept and every Newton step that leaves
    it (or meets ``f' <= 0``) is replaced by bisection, so the iteration always converges.
    Entries with ``y`` outside ``[f(lo), f(hi)]`` converge to the nearest end.
    Stops when every residual is at the dtype's rounding level (``~1e-15`` relative in float64).

    Returns ``x`` with no gradient (use :func:`newton_polish` afterwards).
    """
    y = y.detach()
    lo = torch.broadcast_to(lo.detach(), y.shape).clone()
    hi = torch.broadcast_to(hi.detach(), y.shape).clone()
    x = (lo + hi) / 2 if x0 is None else torch.minimum(torch.maximum(x0.detach(), lo), hi)
    tol = default_tol(y.dtype)
    for _ in range(max_iter):
        fx = f(x) - y
        if bool((fx.abs() <= tol * (1 + y.abs())).all()):
            break
        pos = fx > 0
        hi = torch.where(pos, x, hi)
        lo = torch.where(pos, lo, x)
        d = df(x)
        step_ok = d > 0
        xn = x - fx / torch.where(step_ok, d, torch.ones_like(d))
        inside = step_ok & (xn > lo) & (xn < hi)
        x_new = torch.where(inside, xn, (lo + hi) / 2)
        if bool((x_new == x).all()):
            break
        x = x_new
    return x


@torch.no_grad()
def bisect_sign_change(f: Fn, lo: Tensor, hi: Tensor, iters: int | None = None) -> tuple[Tensor, Tensor]:
    """Root of ``f`` on ``[lo, hi]`` by bisection (elementwise); ``f`` must change sign on the interval.

    Returns ``(x, ok)`` where ``ok`` is False where ``f(lo)`` and ``f(hi)`` have the same sign.
    ``iters`` defaults to enough halvings to reach the dtype's resolution.
    """
    lo, hi = torch.broadcast_tensors(lo.detach(), hi.detach())
    lo, hi = lo.clone(), hi.clone()
    flo, fhi = f(lo), f(hi)
    ok = (torch.sign(flo) * torch.sign(fhi)) <= 0
    s_lo = torch.sign(flo)
    if iters is None:
        iters = 64 if lo.dtype == torch.float64 else 32
    for _ in range(iters):
        mid = (lo + hi) / 2
        fm = f(mid)
        same = torch.sign(fm) == s_lo
        lo = torch.where(same, mid, lo)
        hi = torch.where(same, hi, mid)
    return (lo + hi) / 2, ok


def newton_polish(x_star: Tensor, residual: Fn, deriv: Tensor | None = None) -> Tensor:
    """One differentiable Newton step from the detached root ``x_star`` of ``residual(x) = 0``.

    ``residual`` may depend (differentiably) on other tensors captured in the closure
    (the targets); the returned ``x`` carries the implicit-function gradient.
    ``deriv`` is ``d residual / dx`` at ``x_star``; computed by autograd when omitted.
    Where the derivative is 0 the step is skipped (finite values and gradients).
    """
    x_star = x_star.detach()
    if deriv is None:
        with torch.enable_grad():
            xs = x_star.clone().requires_grad_(True)
            r = residual(xs)
            deriv = torch.autograd.grad(r.sum(), xs, allow_unused=True)[0]
        if deriv is None:
            deriv = torch.zeros_like(x_star)
    deriv = deriv.detach()
    ok = deriv != 0
    return x_star - torch.where(ok, residual(x_star), torch.zeros_like(x_star)) / torch.where(ok, deriv,
                                                                                          torch.ones_like(deriv))


def polyval(coeffs: tuple[float, ...] | list[float], x: Tensor) -> Tensor:
    """``sum_k coeffs[k] * x**k`` by Horner's rule (coefficients in increasing degree)."""
    out = torch.zeros_like(x)
    for c in reversed(coeffs):
        out = out * x + c
    return out


def polyder(coeffs: tuple[float, ...] | list[float]) -> tuple[float, ...]:
    """Coefficients (increasing degree) of the derivative polynomial."""
    return tuple(k * c for k, c in enumerate(coeffs))[1:] or (0.0,)
