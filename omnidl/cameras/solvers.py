"""Small vectorised solvers shared by the camera models.

Every iterative inverse (Kannala–Brandt ``d(theta) = r``, OCamCalib angle, non-central
reflection point) is solved without autograd and then *polished* by one Newton step
that is differentiable: with ``x*`` the (detached) converged root of ``f(x) = y``,
``x = x* - (f(x*) - y) / f'(x*)`` has value ``x*`` (up to rounding) and gradient
``dx/dy = 1 / f'(x*)`` — the implicit-function derivative — so gradients are exact and
do not depend on the number of iterations.

Two-dimensional maps (lens distortion ``(x, y) -> (x_d, y_d)``) use :func:`solve_2d` (damped
Newton, no autograd) and :func:`newton_polish_2d`, whose single step
``x = x* - J(x*)^{-1} (f(x*) - y)`` with ``J`` detached carries ``dx/dy = J^{-1}``.
"""
from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

Fn = Callable[[Tensor], Tensor]
#: ``(..., 2)`` -> ``(..., 2, 2)`` Jacobian ``[[dfx/dx, dfx/dy], [dfy/dx, dfy/dy]]``
JacFn = Callable[[Tensor], Tensor]


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


def _solve_2x2(jac: Tensor, rhs: Tensor) -> tuple[Tensor, Tensor]:
    """``J^{-1} rhs`` for ``jac (..., 2, 2)``, ``rhs (..., 2)`` by Cramer's rule; returns ``(step, det)``.

    Where ``det == 0`` the step is 0 (finite values and gradients).
    """
    a, b, c, d = jac[..., 0, 0], jac[..., 0, 1], jac[..., 1, 0], jac[..., 1, 1]
    det = a * d - b * c
    ok = det != 0
    inv = 1 / torch.where(ok, det, torch.ones_like(det))
    sx = torch.where(ok, (d * rhs[..., 0] - b * rhs[..., 1]) * inv, torch.zeros_like(det))
    sy = torch.where(ok, (a * rhs[..., 1] - c * rhs[..., 0]) * inv, torch.zeros_like(det))
    return torch.stack([sx, sy], -1), det


@torch.no_grad()
def solve_2d(f: Fn, jac: JacFn, y: Tensor, x0: Tensor | None = None, max_norm: float | None = None,
             max_iter: int = 50, max_halvings: int = 12) -> tuple[Tensor, Tensor]:
    """Root of ``f(x) = y`` for a smooth map of the plane, batched: ``x, y (..., 2)``.

    Damped Newton: each step ``-J^{-1} (f(x) - y)`` is halved (up to ``max_halvings`` times) until
    the residual does not grow, and iterates are pulled back radially onto the disk
    ``|x| <= max_norm`` when one is given (the region where the map is known to be invertible).
    An entry stops when its residual is at the dtype's rounding level (``4 eps (1 + |y|)``), when its
    step no longer lowers the residual, or after four damped or pulled-back steps (no root in
    reach: near a regular root Newton takes full steps and converges quadratically). Starts at
    ``x0`` (default ``y``: a distortion is near the identity). ``f`` and ``jac`` must act
    elementwise over the batch dimensions (they are called on the ``(n, 2)`` still-active entries
    only, so the cost follows the hard cases).

    Returns ``(x, converged)`` without gradient (use :func:`newton_polish_2d`); ``converged``
    ``(...)`` is True where the final residual is within ``1000 eps (1 + |y|)`` and ``J`` is regular.
    Entries with non-finite ``y`` come back finite with ``converged=False``.
    """
    shape = y.shape
    y = y.detach().reshape(-1, 2)
    finite = torch.isfinite(y).all(-1)
    y = torch.where(finite.unsqueeze(-1), y, torch.zeros_like(y))
    x = y.clone() if x0 is None else x0.detach().reshape(-1, 2).clone()
    x = torch.where(finite.unsqueeze(-1) & torch.isfinite(x), x, torch.zeros_like(x))
    eps = torch.finfo(y.dtype).eps
    tol = default_tol(y.dtype) * (1 + y.abs().amax(-1))
    bounded = max_norm is not None and math.isfinite(max_norm)

    def clip(z: Tensor) -> tuple[Tensor, Tensor]:
        if not bounded:
            return z, torch.zeros_like(z[:, 0], dtype=torch.bool)
        n = z.norm(dim=-1, keepdim=True)
        out = n > max_norm
        return torch.where(out, z * (max_norm / n.clamp_min(1e-300)), z), out.squeeze(-1)

    def residual(z: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
        e = f(z) - target
        e = torch.where(torch.isfinite(e), e, torch.full_like(e, float("inf")))
        return e, e.abs().amax(-1)

    x, _ = clip(x)
    e, rn = residual(x, y)
    idx = torch.nonzero(~(rn <= tol)).squeeze(-1)
    strikes = torch.zeros_like(idx)
    for _ in range(max_iter):
        if idx.numel() == 0:
            break
        xa, ya, ea, ra = x[idx], y[idx], e[idx], rn[idx]
        step, _ = _solve_2x2(jac(xa), ea)
        t = torch.ones_like(ra)
        xn, clipped = clip(xa - step)
        en, rnn = residual(xn, ya)
        for _ in range(max_halvings):  # backtrack where the residual grew
            worse = ~(rnn <= ra)
            if not bool(worse.any()):
                break
            t = torch.where(worse, t / 2, t)
            xt, ct = clip(xa - t.unsqueeze(-1) * step)
            et, rnt = residual(xt, ya)
            w = worse.unsqueeze(-1)
            xn, en, rnn = torch.where(w, xt, xn), torch.where(w, et, en), torch.where(worse, rnt, rnn)
            clipped = torch.where(worse, ct, clipped)
        progress = rnn < ra
        x[idx] = torch.where(progress.unsqueeze(-1), xn, xa)
        e[idx] = torch.where(progress.unsqueeze(-1), en, ea)
        rn[idx] = torch.where(progress, rnn, ra)
        strikes = strikes + (clipped | (t < 1)).long()
        active = progress & ~(rn[idx] <= tol[idx]) & (strikes < 4)
        idx, strikes = idx[active], strikes[active]
    _, det = _solve_2x2(jac(x), torch.zeros_like(x))
    converged = finite & (rn <= 1000 * eps * (1 + y.abs().amax(-1))) & (det != 0) & torch.isfinite(det)
    return x.reshape(shape), converged.reshape(shape[:-1])


def newton_polish_2d(x_star: Tensor, residual: Fn, jac: Tensor) -> Tensor:
    """One differentiable 2-D Newton step ``x* - J^{-1} residual(x*)`` from the detached root ``x_star``.

    ``residual (..., 2) -> (..., 2)`` may depend differentiably on other tensors (the targets);
    ``jac (..., 2, 2)`` is ``d residual / dx`` at ``x_star`` (detached here). The value equals
    ``x_star`` up to rounding and the gradient is the implicit-function derivative ``-J^{-1} dr/dy``.
    Where ``det J = 0`` the step is skipped.
    """
    x_star = x_star.detach()
    step, _ = _solve_2x2(jac.detach(), residual(x_star))
    return x_star - step
