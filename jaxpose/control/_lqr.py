"""Time-varying LQR by the Riccati recursion (``lax.scan``, Cholesky solves).

Problem (one element; batches by ``jax.vmap``, which keeps everything that does not
depend on the batched argument — e.g. the Riccati matrices when only ``x0`` is
batched — unbatched)::

    min  Σ_{t<T} ½ τ_tᵀ C_t τ_t + c_tᵀ τ_t  +  ½ x_Tᵀ C_T x_T + c_Tᵀ x_T,   τ_t = [x_t; u_t]
    s.t. x_{t+1} = F_t τ_t + f_t,   x_0 = x0.

Shapes: F (T, n, n+m), f (T, n), C (T, n+m, n+m), c (T, n+m), C_T (n, n), c_T (n,).
The optimal policy is ``u_t = K_t x_t + k_t``. An optional ``free`` mask (T, m) fixes
the masked-out controls to zero (used for active box constraints in the implicit
gradient of MPC).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve

from .._checks import check_count
from .._dtypes import keep_dtypes
from .._precision import full_precision
from ..dynamics._checks import as_array, start_step, window_message
from ..dynamics._system import LTI, LTV, System
from ..lie._base import runtime_check
from ..results import Results
from ._boxqp import _box_qp, free_block
from ._cost import Cost, QuadraticCost

Array = jax.Array

class BackwardOut(NamedTuple):
    """One Riccati step: policy (K, k), value (V, v), expected-decrease terms and flags."""

    K: Array
    k: Array
    V: Array
    v: Array
    dj1: Array
    dj2: Array
    ok: Array
    free: Array
    L: Array


def backward_step(
    V: Array,
    v: Array,
    F: Array,
    f: Array,
    C: Array,
    c: Array,
    *,
    reg: Any = 0.0,
    free: Array | None = None,
    box: tuple[Array, Array, Array] | None = None,
    box_iters: int = 20,
    unroll: bool = False,
    safe: bool = False,
) -> BackwardOut:
    """One step of the recursion: from the value ``(V, v)`` at ``t+1`` to the policy and
    value at ``t``. ``reg`` adds μI to Q_uu for the policy (Levenberg–Marquardt style).
    ``box = (lo, hi, k_warm)`` solves the control-limited step by projected Newton.
    ``safe`` replaces a non-PD Q_uu by the identity before factorising, so that reverse
    mode through rejected (masked-out) iterations stays finite."""
    n = F.shape[0]
    FtV = F.T @ V
    Q = C + FtV @ F
    Q = 0.5 * (Q + Q.T)
    q = c + FtV @ f + F.T @ v
    Qxx, Qux, Quu = Q[:n, :n], Q[n:, :n], Q[n:, n:]
    qx, qu = q[:n], q[n:]
    m = Quu.shape[0]
    Hu = Quu + reg * jnp.eye(m, dtype=Quu.dtype)
    if safe:
        probe = jnp.linalg.cholesky(jax.lax.stop_gradient(Hu))
        Hu = jnp.where(jnp.all(jnp.isfinite(probe)), Hu, jnp.eye(m, dtype=Hu.dtype))
    if box is not None:
        lo, hi, k_warm = box
        res = _box_qp(Hu, qu, lo, hi, k_warm, box_iters, unroll)
        k, fr, L, ok = res.x, res.free, res.L, res.ok
        K = -cho_solve((L, True), jnp.where(fr[:, None], Qux, 0.0))
        K = jnp.where(fr[:, None], K, 0.0)
    else:
        fr = jnp.ones((m,), bool) if free is None else free
        Hf = Hu if free is None else free_block(Hu, free)
        L = jnp.linalg.cholesky(Hf)
        ok = jnp.all(jnp.isfinite(L))
        # K and k are solved separately so that, under vmap, a batched linear term (k)
        # does not make the Riccati matrices (K, V) batched.
        Qux_f = Qux if free is None else jnp.where(free[:, None], Qux, 0.0)
        qu_f = qu if free is None else jnp.where(free, qu, 0.0)
        K = -cho_solve((L, True), Qux_f)
        k = -cho_solve((L, True), qu_f)
        if free is not None:
            K = jnp.where(free[:, None], K, 0.0)
            k = jnp.where(free, k, 0.0)
    QuuK = Quu @ K
    V_new = Qxx + K.T @ Qux + Qux.T @ K + K.T @ QuuK
    V_new = 0.5 * (V_new + V_new.T)
    v_new = qx + K.T @ qu + Qux.T @ k + QuuK.T @ k
    dj1 = k @ qu
    dj2 = 0.5 * k @ (Quu @ k)
    return BackwardOut(K, k, V_new, v_new, dj1, dj2, ok, fr, L)


@full_precision
def riccati(
    F: Array,
    f: Array,
    C: Array,
    c: Array,
    CT: Array,
    cT: Array,
    free: Array | None = None,
    reg: Any = 0.0,
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Backward recursion: ``K`` (T, m, n), ``k`` (T, m), ``V`` (T+1, n, n), ``v``
    (T+1, n) (``V[T] = C_T``), ``ok`` (every Q_uu positive definite) and ``L``
    (T, m, m), the lower Cholesky factors of the (``reg``-regularised) Q_uu. ``free``
    (T, m) bools: inputs held at 0 where False."""

    def step(carry: tuple[Array, Array], inp: tuple[Array, ...]):
        V, v = carry
        if free is None:
            Ft, ft, Ct, ct = inp
            fr = None
        else:
            Ft, ft, Ct, ct, fr = inp
        out = backward_step(V, v, Ft, ft, Ct, ct, reg=reg, free=fr)
        return (out.V, out.v), (out.K, out.k, out.V, out.v, out.ok, out.L)

    xs = (F, f, C, c) if free is None else (F, f, C, c, free)
    _, (K, k, V, v, ok, L) = jax.lax.scan(step, (CT, cT), xs, reverse=True)
    V = jnp.concatenate([V, CT[None]], 0)
    v = jnp.concatenate([v, cT[None]], 0)
    return K, k, V, v, jnp.all(ok), L


def policy_rollout(F: Array, f: Array, K: Array, k: Array, x0: Array) -> tuple[Array, Array]:
    """Forward pass ``u_t = K_t x_t + k_t``, ``x_{t+1} = F_t [x_t; u_t] + f_t``:
    xs (T+1, n), us (T, m)."""

    def step(x: Array, inp: tuple[Array, ...]):
        Ft, ft, Kt, kt = inp
        u = Kt @ x + kt
        x_next = keep_dtypes(Ft @ jnp.concatenate([x, u]) + ft, x)  # x0's dtype
        return x_next, (x_next, u)

    _, (xs, us) = jax.lax.scan(step, x0, (F, f, K, k))
    return jnp.concatenate([x0[None], xs], 0), us


def quadratic_total(C: Array, c: Array, CT: Array, cT: Array, xs: Array, us: Array) -> Array:
    """Cost of a trajectory under the quadratic cost (C, c, C_T, c_T)."""
    tau = jnp.concatenate([xs[:-1], us], -1)
    stage = 0.5 * jnp.einsum("ti,tij,tj->", tau, C, tau) + jnp.einsum("ti,ti->", c, tau)
    xT = xs[-1]
    return stage + 0.5 * xT @ (CT @ xT) + cT @ xT


class LQRSolution(eqx.Module):
    """``x`` (…, T+1, n) (x0 first), ``u`` (…, T, m), ``cost`` (…), feedback ``K``
    (…, T, m, n) and ``k`` (…, T, m), ``status`` (…) int32
    :class:`~jaxpose.Results` code (CONVERGED 0 or NON_FINITE 3)."""

    x: Array
    u: Array
    cost: Array
    K: Array
    k: Array
    status: Array

    @property
    def status_name(self) -> Any:
        """``status`` as text (``"converged"``, ...; an array of names when batched), by
        :meth:`jaxpose.Results.name_of`."""
        return Results.name_of(self.status)


@eqx.filter_jit
@full_precision
def lqr_solve(
    F: Array,
    f: Array,
    C: Array,
    c: Array,
    x0: Array,
    CT: Array | None = None,
    cT: Array | None = None,
    free: Array | None = None,
) -> LQRSolution:
    """Solve the LQR problem above for one element (see the module docstring).

    Compiled with ``eqx.filter_jit`` (shape checks run at trace time); new arrays of the
    same shapes reuse the compiled program."""
    F, f, C, c, x0 = (
        as_array(a, nm) for a, nm in ((F, "F"), (f, "f"), (C, "C"), (c, "c"), (x0, "x0"))
    )
    _check_lqr_shapes(F, f, C, c, x0)
    n = F.shape[1]
    CT = jnp.zeros((n, n), C.dtype) if CT is None else as_array(CT, "CT", 2)
    cT = jnp.zeros((n,), C.dtype) if cT is None else as_array(cT, "cT", 1)
    if CT.shape != (n, n) or cT.shape != (n,):
        raise ValueError(
            f"CT, cT: expected shapes ({n}, {n}) and ({n},), got "
            f"{tuple(CT.shape)} and {tuple(cT.shape)}"
        )
    if free is not None:
        free = jnp.asarray(free)
        T, m = F.shape[0], F.shape[2] - n
        if free.shape != (T, m) or free.dtype != jnp.bool_:
            raise ValueError(f"free: expected a ({T}, {m}) (T, m) bool mask (False: the input "
                             f"is held at 0), got {free.dtype} {tuple(free.shape)}")
    K, k, _, _, ok, _ = riccati(F, f, C, c, CT, cT, free)
    xs, us = policy_rollout(F, f, K, k, x0)
    cost = quadratic_total(C, c, CT, cT, xs, us)
    # the cost too: a state of 1e200 has a finite trajectory but a cost that overflows
    finite = ok & jnp.all(jnp.isfinite(xs)) & jnp.all(jnp.isfinite(us)) & jnp.isfinite(cost)
    status = jnp.where(finite, Results.CONVERGED, Results.NON_FINITE).astype(jnp.int32)
    return LQRSolution(xs, us, cost, K, k, status)


def _check_lqr_shapes(F: Array, f: Array, C: Array, c: Array, x0: Array) -> None:
    if F.ndim != 3:
        raise ValueError(f"F: expected (T, n, n+m), got {tuple(F.shape)}")
    T, n, nm = F.shape
    if nm <= n:
        raise ValueError(f"F: expected (T, n, n+m) with m ≥ 1 inputs, got {tuple(F.shape)}")
    if f.shape != (T, n):
        raise ValueError(f"f: expected shape ({T}, {n}), got {tuple(f.shape)}")
    if C.shape != (T, nm, nm):
        raise ValueError(f"C: expected shape ({T}, {nm}, {nm}) (T, n+m, n+m), got {tuple(C.shape)}")
    if c.shape != (T, nm):
        raise ValueError(f"c: expected shape ({T}, {nm}), got {tuple(c.shape)}")
    if x0.shape != (n,):
        raise ValueError(
            f"x0: expected shape ({n},) (n = F.shape[1] states), got {tuple(x0.shape)}"
        )


def lq_problem(
    system: System, cost: QuadraticCost, horizon: int, t0: Any = 0
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """``(F, f, C, c, C_T, c_T)`` for a linear system and quadratic cost over the steps
    ``t0`` … ``t0 + horizon − 1`` (an LTV system's or time-varying cost's steps there;
    ``t0`` may be traced)."""
    horizon = check_count(horizon, "horizon")
    if not isinstance(system, (LTI, LTV)):
        raise TypeError(
            f"system: LQR needs an LTI or LTV system, got {type(system).__name__};"
            f" use ilqr / MPC for nonlinear dynamics"
        )
    if not isinstance(cost, QuadraticCost):
        raise TypeError(
            f"cost: LQR needs a QuadraticCost, got {type(cost).__name__}; use "
            f"ilqr / MPC for general costs"
        )
    n, m = system.state_dim, system.input_dim
    C, c, CT, cT = check_quadratic_cost(cost, n, m, horizon, f"A is {n}×{n}, B is {n}×{m}",
                                        t0)
    F, f = system.matrices(horizon, t0)
    return F, f, C, c, CT, cT


def check_quadratic_cost(
    cost: QuadraticCost, n: int, m: int, horizon: int, sizes: str, t0: Any = 0
) -> tuple[Array, Array, Array, Array]:
    """:meth:`QuadraticCost.stacked` after checking its size ``n + m`` (``sizes`` says
    where n and m come from): raises naming ``Q``, ``QT``, ``pT`` or ``horizon``."""
    if cost.size != n + m:
        raise ValueError(
            f"Q: expected size n + m = {n} + {m} = {n + m} ({sizes}), got {cost.size}"
        )
    return cost.stacked(horizon, n, t0)


def time_varying_steps(system: System, cost: Cost) -> list[tuple[int, str]]:
    """``(k, whose)`` for each time-varying part: a time-varying quadratic cost's and an
    LTV system's numbers of time steps."""
    steps = []
    if isinstance(cost, QuadraticCost) and cost.time_varying is not None:
        steps.append((cost.time_varying, "cost's"))
    if isinstance(system, LTV):
        steps.append((system.horizon, "LTV system's"))
    return steps


def check_start_step(system: System, cost: Cost, T: int, t0: Any) -> Array:
    """``t0`` as an array; with a time-varying cost or LTV system of k ≥ T steps, raises
    (eagerly, or ``eqx.error_if`` under ``jit``) unless 0 ≤ t0 ≤ k − T: JAX indexing
    would silently clamp or wrap. (k < T raises in :func:`_ilqr` naming the horizon.)"""
    t0 = jnp.asarray(start_step(t0), jnp.int32)
    for k, what in time_varying_steps(system, cost):
        if k >= T:
            t0 = runtime_check(t0, jnp.any((t0 < 0) | (t0 + T > k)),
                               window_message(k, T, what))
    return t0


def lqr(system: System, cost: QuadraticCost, x0: Any, horizon: int, t0: Any = 0
        ) -> LQRSolution:
    """LQR for an :class:`LTI`/:class:`LTV` system and a :class:`QuadraticCost` over
    ``horizon`` steps from step ``t0`` (the steps ``t0 … t0 + horizon − 1`` of an LTV
    system or time-varying cost; outside theirs raises). ``x0`` (n,) or batched (..., n)
    (vmapped; the Riccati recursion is computed once for the whole batch).

    Compiled with ``eqx.filter_jit``: ``horizon`` (a Python int) is static, the arrays of
    ``system``, ``cost`` and ``x0`` and the step ``t0`` are traced; shape checks run at
    trace time, ``t0``'s range eagerly (``eqx.error_if`` when it is traced)."""
    check_count(horizon, "horizon")
    return _lqr(system, cost, x0, horizon, check_start_step(system, cost, horizon, t0))


@eqx.filter_jit
@full_precision
def _lqr(system: System, cost: QuadraticCost, x0: Any, horizon: int, t0: Array
         ) -> LQRSolution:
    F, f, C, c, CT, cT = lq_problem(system, cost, horizon, t0)
    x0 = as_array(x0, "x0")
    n = F.shape[1]
    if x0.ndim == 0 or x0.shape[-1] != n:
        raise ValueError(f"x0: expected shape (..., {n}) (n = A.shape[0]), got {tuple(x0.shape)}")
    solve = lambda x: lqr_solve(F, f, C, c, x, CT, cT)
    if x0.ndim == 1:
        return solve(x0)
    batch = x0.shape[:-1]
    out = jax.vmap(solve)(x0.reshape(-1, n))
    return jax.tree.map(lambda a: a.reshape(*batch, *a.shape[1:]), out)


class LQR(eqx.Module):
    """LQR as a module: ``LQR(system, cost, horizon)(x0) → LQRSolution``.

    Box control limits are not part of LQR: passing ``u_lower``/``u_upper`` raises
    (use :class:`~jaxpose.control.MPC` or :func:`~jaxpose.control.ilqr`, which honour
    them)."""

    system: System
    cost: QuadraticCost
    horizon: int = eqx.field(static=True)

    def __init__(self, system: System, cost: QuadraticCost, horizon: int):
        lq_problem(system, cost, horizon)  # validates
        self.system, self.cost, self.horizon = system, cost, check_count(horizon, "horizon")

    def __call__(self, x0: Any, u_lower: Any = None, u_upper: Any = None, t0: Any = 0
                 ) -> LQRSolution:
        """Solve the LQ problem from ``x0`` (n,) or a batch (…, n) at step ``t0`` (alias of
        :func:`lqr`).

        LQR has no control limits: passing ``u_lower``/``u_upper`` raises ``ValueError``.
        """
        if u_lower is not None or u_upper is not None:
            raise ValueError(
                "u_lower/u_upper: LQR has no control limits; use MPC or ilqr, "
                "which enforce them by projected Newton"
            )
        return lqr(self.system, self.cost, x0, self.horizon, t0)
