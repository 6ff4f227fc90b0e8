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
        inside = step_ok & (xn >= lo) & (xn <= hi)
        x_new = torch.where(inside, xn, (lo + hi) / 2)
        stalled = bool(((x_new - x).abs() <= 2 * torch.finfo(x.dtype).eps * x.abs().clamp_min(1e-30)).all())
        x = x_new
        if stalled:
            break
    return x


@torch.no_grad()
def bracketed_root(f: Fn, lo: Tensor, hi: Tensor, max_iter: int = 100) -> tuple[Tensor, Tensor]:
    """Root of ``f`` on ``[lo, hi]`` (elementwise) where ``f`` changes sign on the interval.

    Illinois-modified regula falsi: derivative-free, always keeps a bracket, superlinear
    convergence (about 10 iterations to float64 resolution instead of 64 bisections). Stops
    when every estimate has stopped moving at the dtype's resolution.

    Returns ``(x, ok)`` where ``ok`` is False where ``f(lo)`` and ``f(hi)`` have the same sign.
    """
    a, b = torch.broadcast_tensors(lo.detach(), hi.detach())
    a, b = a.clone(), b.clone()
    fa, fb = f(a), f(b)
    ok = (torch.sign(fa) * torch.sign(fb)) <= 0
    eps = torch.finfo(a.dtype).eps
    side = torch.zeros_like(a)  # +1: b was kept last time, -1: a was kept last time
    x = torch.where(fa == 0, a, b)
    for _ in range(max_iter):
        den = fb - fa
        x_new = torch.where(den != 0, b - fb * (b - a) / torch.where(den != 0, den, torch.ones_like(den)), (a + b) / 2)
        bad = ~((x_new >= torch.minimum(a, b)) & (x_new <= torch.maximum(a, b)))
        x_new = torch.where(bad, (a + b) / 2, x_new)
        fx = f(x_new)
        same_as_b = torch.sign(fx) == torch.sign(fb)
        # replace the end with the same sign; Illinois: halve the other end's value if it is kept twice
        a_keep = same_as_b
        b_new = torch.where(same_as_b, x_new, b)
        fb_new = torch.where(same_as_b, fx, fb)
        a_new = torch.where(same_as_b, a, x_new)
        fa_new = torch.where(same_as_b, fa, fx)
        fa_new = torch.where(a_keep & (side == -1), fa_new / 2, fa_new)
        fb_new = torch.where(~a_keep & (side == 1), fb_new / 2, fb_new)
        side = torch.where(a_keep, -torch.ones_like(side), torch.ones_like(side))
        a, fa, b, fb = a_new, fa_new, b_new, fb_new
        done = ((x_new - x).abs() <= 4 * eps * x_new.abs()) | (fx == 0)
        x = x_new
        if bool((done | ~ok).all()):
            break
    return x, ok


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
