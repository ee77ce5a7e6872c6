"""Box-constrained QP by projected Newton (Bertsekas 1982), as used in control-limited
DDP (Tassa et al. 2014) and differentiable MPC (Amos et al. 2018):

    min_x ½ xᵀ H x + gᵀ x   s.t.  lo ≤ x ≤ hi.

Each iteration finds the clamped set (at a bound with the gradient pushing outwards),
takes a Newton step on the free coordinates (Cholesky of the free block) and a projected
Armijo line search. Shapes: H (m, m), g (m,), lo/hi (m,) (±inf allowed).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import cho_solve

from .._checks import check_count
from .._precision import full_precision
from ..lie._base import runtime_check

Array = jax.Array

_ALPHAS = 0.5 ** np.arange(12.0)  # NumPy: a jnp constant compiled at import
_ARMIJO = 0.1


class BoxQPResult(NamedTuple):
    """Solution ``x``, ``free`` mask (True where not clamped), Cholesky factor ``L`` of
    the free block (identity rows/cols on clamped coordinates), ``ok`` (finite, PD)."""

    x: Array
    free: Array
    L: Array
    ok: Array


def free_block(H: Array, free: Array) -> Array:
    """``H`` restricted to the free coordinates, identity on the clamped ones."""
    both = free[:, None] & free[None, :]
    eye = jnp.eye(H.shape[-1], dtype=H.dtype)
    return jnp.where(both, H, eye)


def _clamped(x: Array, grad: Array, lo: Array, hi: Array) -> Array:
    return ((x <= lo) & (grad > 0)) | ((x >= hi) & (grad < 0))


@full_precision
def box_qp(
    H: Array, g: Array, lo: Array, hi: Array, x0: Array, iters: int = 20, unroll: bool = False
) -> BoxQPResult:
    """Projected Newton for the box QP, warm-started at ``clip(x0, lo, hi)``: H (m, m),
    g, lo, hi, x0 (m,) (±inf bounds allowed).

    ``unroll=True`` runs exactly ``iters`` (an int ≥ 1) iterations with ``lax.scan``
    (reverse-mode differentiable); otherwise a ``while_loop`` stops at convergence.
    Shapes are checked at trace time; NaN or crossed bounds (``lo > hi``, an empty box)
    raise, eagerly or through ``eqx.error_if`` under ``jit``."""
    check_count(iters, "iters")
    H, g, lo, hi, x0 = (jnp.asarray(a) for a in (H, g, lo, hi, x0))
    m = g.shape[0] if g.ndim == 1 else -1
    if g.ndim != 1 or H.shape != (m, m):
        raise ValueError(f"H, g: expected shapes (m, m) and (m,), got {tuple(H.shape)} and "
                         f"{tuple(g.shape)}")
    for arr, name in ((lo, "lo"), (hi, "hi"), (x0, "x0")):
        if arr.shape != (m,):
            raise ValueError(f"{name}: expected shape ({m},) like g, got {tuple(arr.shape)}")
    lo, hi = checked_box(lo, hi, "lo", "hi")
    return _box_qp(H, g, lo, hi, x0, iters, unroll)


def checked_box(lo: Array, hi: Array, lo_name: str, hi_name: str) -> tuple[Array, Array]:
    """``(lo, hi)``, raising where either holds a NaN or ``lo > hi`` (an empty box):
    eagerly when the values are known, else through ``eqx.error_if``."""
    lo = runtime_check(lo, jnp.any(jnp.isnan(lo)),
                       f"{lo_name}: contains NaN (use -inf for an unbounded input)")
    hi = runtime_check(hi, jnp.any(jnp.isnan(hi)),
                       f"{hi_name}: contains NaN (use +inf for an unbounded input)")
    lo = runtime_check(lo, jnp.any(lo > hi),
                       f"{lo_name}, {hi_name}: expected {lo_name} ≤ {hi_name} everywhere")
    return lo, hi


def _box_qp(H: Array, g: Array, lo: Array, hi: Array, x0: Array, iters: int, unroll: bool
            ) -> BoxQPResult:
    """:func:`box_qp` without its checks (the solvers check their bounds once)."""
    q = lambda z: 0.5 * z @ (H @ z) + g @ z
    x = jnp.clip(x0, lo, hi)

    def step(x: Array) -> tuple[Array, Array]:
        grad = H @ x + g
        free = ~_clamped(x, grad, lo, hi)
        L = jnp.linalg.cholesky(free_block(H, free))
        dx = -cho_solve((L, True), jnp.where(free, grad, 0.0))
        dx = jnp.where(free, dx, 0.0)
        fx = q(x)
        cands = jnp.clip(x[None] + jnp.asarray(_ALPHAS[:, None], x.dtype) * dx[None], lo, hi)
        fc = jax.vmap(q)(cands)
        decrease = fc <= fx + _ARMIJO * ((cands - x[None]) @ grad)
        good = decrease & jnp.isfinite(fc)
        idx = jnp.argmax(good)
        x_new = jnp.where(jnp.any(good), cands[idx], x)
        moved = jnp.max(jnp.abs(x_new - x)) > 0
        return x_new, moved & jnp.all(jnp.isfinite(L))

    if unroll:

        def scan_body(x: Array, _: None) -> tuple[Array, None]:
            x_new, _moved = step(x)
            return x_new, None

        x, _ = jax.lax.scan(scan_body, x, None, length=iters)
    else:

        def cond(c: tuple[Array, Array, Array]) -> Array:
            _, moved, i = c
            return moved & (i < iters)

        def body(c: tuple[Array, Array, Array]) -> tuple[Array, Array, Array]:
            x, _, i = c
            x_new, moved = step(x)
            return x_new, moved, i + 1

        x, _, _ = jax.lax.while_loop(cond, body, (x, jnp.array(True), jnp.array(0)))
    grad = H @ x + g
    free = ~_clamped(x, grad, lo, hi)
    L = jnp.linalg.cholesky(free_block(H, free))
    ok = jnp.all(jnp.isfinite(L)) & jnp.all(jnp.isfinite(x))
    return BoxQPResult(x, free, L, ok)
