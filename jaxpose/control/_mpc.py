"""Differentiable model-predictive control (Amos et al. 2018, "Differentiable MPC").

:class:`MPC` solves the finite-horizon problem from a state ``x0`` — by one Riccati
pass when the system is linear (``LTI``/``LTV``), the cost quadratic and there are no
control limits, by :func:`~jaxpose.control.ilqr` otherwise — and differentiates the
solution with respect to every array in the system (dynamics parameters), the cost
(weights) and ``x0``:

* ``gradient="implicit"`` (default): implicit function theorem at the fixed point. The
  KKT system of the trajectory optimisation is symmetric with the LQR structure, so the
  tangent of the solution is one extra LQR solve with the Lagrangian Hessian (zero
  initial state; active control limits held at their own tangents), a ``custom_jvp``
  written with differentiable operations: reverse mode is its transpose and
  differentiating it again gives exact derivatives of any order (``jax.hessian``,
  ``jacfwd(jacrev(...))``). It holds at a converged solution that is a strict minimum
  only: differentiating a solve that stopped otherwise (``status`` not converged), or
  one whose Q_uu is not positive definite, raises (in reverse mode where its cotangent
  is nonzero: a batch's loss may mask it out).
* ``gradient="unroll"``: reverse mode through the solver iterations (``max_iter`` of
  them, in ``lax.scan``).

Receding horizon: :meth:`MPC.control` returns the first control and a shifted warm start;
:func:`closed_loop` simulates a plant under MPC with ``lax.scan``.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_count, count_field
from .._precision import full_precision
from ..dynamics._checks import as_array
from ..dynamics._system import LTI, LTV, System
from ..optim._implicit import converged_only, refused_where_used, with_start
from ..optim._implicit import jvp_where as _jvp_where
from ..results import Results
from ._cost import Cost, QuadraticCost
from ._ilqr import ILQRSolution, _bounds, _dynamics_jacobians, ilqr
from ._lqr import (
    check_start_step,
    lq_problem,
    policy_rollout,
    riccati,
    time_varying_steps,
)

Array = jax.Array

GRADIENTS = ("implicit", "unroll")
SOLVERS = ("auto", "lqr", "ilqr")


class MPCSolution(eqx.Module):
    """``x`` (…, T+1, n), ``u`` (…, T, m), ``cost`` (…), ``status`` (…) (a
    :class:`~jaxpose.Results` code: CONVERGED 0, MAX_STEPS 1, DIVERGED 2 (iLQR stalled),
    NON_FINITE 3), ``iterations`` (…)."""

    x: Array
    u: Array
    cost: Array
    status: Array
    iterations: Array

    @property
    def status_name(self) -> Any:
        """``status`` as text (``"converged"``, ...; an array of names when batched), by
        :meth:`jaxpose.Results.name_of`."""
        return Results.name_of(self.status)


class _Config(eqx.Module):
    horizon: int = eqx.field(static=True)
    solver: str = eqx.field(static=True)
    max_iter: int = eqx.field(static=True)
    tol: float | None = eqx.field(static=True)
    unroll: bool = eqx.field(static=True)
    box_iters: int = eqx.field(static=True)


def _use_lqr(system: System, cost: Cost, bounds: Any, solver: str) -> bool:
    lq = isinstance(system, (LTI, LTV)) and isinstance(cost, QuadraticCost) and bounds is None
    if solver == "lqr" and not lq:
        raise ValueError(
            "solver: 'lqr' needs an LTI/LTV system, a QuadraticCost and no "
            "control limits; use 'ilqr' or 'auto'"
        )
    return solver == "lqr" or (solver == "auto" and lq)


def _solve(
    system: System, cost: Cost, x0: Array, u_init: Array, bounds: Any, t0: Array,
    cfg: _Config
) -> tuple[Array, Array, Array, Array]:
    """Forward solve for one element from step ``t0``: ``(x, u, status, iterations)``."""
    if _use_lqr(system, cost, bounds, cfg.solver):
        F, f, C, c, CT, cT = lq_problem(system, cost, cfg.horizon, t0)
        K, k, _, _, ok, _ = riccati(F, f, C, c, CT, cT)
        xs, us = policy_rollout(F, f, K, k, x0)
        finite = ok & jnp.all(jnp.isfinite(xs)) & jnp.all(jnp.isfinite(us))
        status = jnp.where(finite, Results.CONVERGED, Results.NON_FINITE).astype(jnp.int32)
        return xs, us, status, jnp.array(1)
    lo, hi = (None, None) if bounds is None else bounds
    s: ILQRSolution = ilqr(
        system,
        cost,
        x0,
        u_init,
        u_lower=lo,
        u_upper=hi,
        max_iter=cfg.max_iter,
        tol=cfg.tol,
        unroll=cfg.unroll,
        box_iters=cfg.box_iters,
        t0=t0,
    )
    return s.x, s.u, s.status, s.iterations


# ----------------------------------------------------------------------------------
# Implicit differentiation
# ----------------------------------------------------------------------------------
@eqx.filter_custom_jvp
def _solve_implicit(
    params: tuple[System, Cost, Array], u_init: Array, bounds: Any, t0: Array, *,
    cfg: _Config
) -> tuple[Array, Array, Array, Array]:
    system, cost, x0 = params
    return _solve(system, cost, x0, u_init, bounds, t0, cfg)


@_solve_implicit.def_jvp
@full_precision  # traced when differentiated, outside the entry point
def _solve_implicit_jvp(primals: tuple[Any, ...], tangents: tuple[Any, ...], *, cfg: _Config):
    params, u_init, bounds, t0 = primals
    t_params, t_u_init, t_bounds, _ = tangents
    out = _solve_implicit(params, u_init, bounds, t0, cfg=cfg)  # differentiable again
    xs, us = out[:2]
    where = "MPC(gradient='implicit')"
    remedy = ("Give iLQR more iterations or looser tolerances, or differentiate the iterates "
              "with gradient='unroll'.")
    tangent, strict = _trajectory_tangent(params, t_params, xs, us, bounds, t_bounds, t0)
    wx, wu = converged_only(refused_where_used(tangent, ~strict, _NOT_STRICT_MINIMUM),
                            out[2], where, remedy)
    wx, wu = with_start((wx, wu), t_u_init, out[2], where, remedy)
    return out, (wx, wu, None, None)


_NOT_STRICT_MINIMUM = (
    "MPC: cannot differentiate the solution (gradient='implicit'): the Hessian of the "
    "Lagrangian in the free controls (Q_uu of the tangent LQR problem) is not positive "
    "definite at some step of the solution, so the implicit function theorem does not give "
    "its derivative. Either the solver stopped at a stationary point that is not a strict "
    "minimum (a saddle or maximum in u), or the cost is not strictly convex in u there "
    "(e.g. no control cost at a step). Add control cost, start from another u_init, or use "
    "gradient='unroll' (the derivative of the iterates).")


def _trajectory_tangent(
    params: tuple[System, Cost, Array],
    t_params: Any,
    xs: Array,
    us: Array,
    bounds: Any,
    t_bounds: Any,
    t0: Array,
) -> tuple[tuple[Array, Array], Array]:
    """Tangent ``(ẋ (T+1, n), u̇ (T, m))`` of a locally optimal trajectory ``(xs, us)``
    over the steps ``t0`` … ``t0 + T − 1`` along the parameter tangent ``t_params`` (and
    ``t_bounds``, moving the active limits), by the implicit function theorem on the KKT
    conditions. The tangent system is
    itself an LQR problem: min ½ wᵀ H w + ċᵀ w s.t. w_{t+1} = F_t w_t + ḟ_t, w_0 = ẋ0,
    with H the Lagrangian Hessian, F the dynamics Jacobians, ċ = ∂_θ∇_τL·θ̇ and
    ḟ = ∂_θ f·θ̇ (active control limits held at their own tangents). Linear in the
    tangents and written with differentiable operations on ``(xs, us)``, so reverse mode
    is its transpose and every order is exact. Also returns whether the solution is a
    strict minimum (every Q_uu positive definite): where it is not, the derivative does
    not exist, and the tangent is that of a stand-in problem (identity Hessians), finite,
    for the caller to refuse where it is used."""
    system, cost, x0 = params
    T, m = us.shape
    n = xs.shape[-1]
    ts = t0 + jnp.arange(T)
    F = _dynamics_jacobians(system, xs[:-1], us, ts)
    # Costates: λ_T = ∇ℓ_T, λ_t = ∇_x ℓ_t + A_tᵀ λ_{t+1}.
    H, g = jax.vmap(cost.quadratize)(xs[:-1], us, ts)
    HT, gT = cost.quadratize_terminal(xs[-1])

    def costate(lam: Array, inp: tuple[Array, Array]):
        Ft, gt = inp
        return gt[:n] + Ft[:, :n].T @ lam, lam

    _, lam_next = jax.lax.scan(costate, gT, (F, g), reverse=True)  # λ_{t+1}, (T, n)
    if not system.is_linear:

        def dyn_hess(x: Array, u: Array, t: Array, lam: Array) -> Array:
            fn = lambda tau: lam @ system.state_transition(tau[:n], tau[n:], t)
            return jax.hessian(fn)(jnp.concatenate([x, u]))

        H = H + jax.vmap(dyn_hess)(xs[:-1], us, ts, lam_next)

    def kkt_terms(p: tuple[System, Cost, Array]) -> tuple[Array, Array, Array, Array]:
        """∇_τ L_t (T, n+m), ∇ℓ_T (n,), f_t (T, n) at the fixed trajectory, and x0."""
        sys_, cost_, x0_ = p

        def stage(x: Array, u: Array, t: Array, lam: Array) -> tuple[Array, Array]:
            def lag(tau: Array) -> Array:
                xx, uu = tau[:n], tau[n:]
                return cost_.stage(xx, uu, t) + lam @ sys_.state_transition(xx, uu, t)

            return jax.grad(lag)(jnp.concatenate([x, u])), sys_.state_transition(x, u, t)

        c, f = jax.vmap(stage)(xs[:-1], us, ts, lam_next)
        return c, jax.grad(cost_.terminal)(xs[-1]), f, x0_

    _, (c_dot, cT_dot, f_dot, x0_dot) = _jvp_where(kkt_terms, params, t_params)
    free, d = None, jnp.zeros_like(us)
    if bounds is not None:
        lo, hi = bounds
        at_lo, at_hi = us <= lo, us >= hi
        free = ~(at_lo | at_hi)
        if t_bounds is not None:  # active limits move the clamped controls
            t_lo, t_hi = t_bounds
            if t_lo is not None:
                d = d + jnp.where(at_lo, t_lo, 0.0)
            if t_hi is not None:
                d = d + jnp.where(at_hi & ~at_lo, t_hi, 0.0)
        # the fixed part d of u̇ enters the dynamics offset and the linear cost term
        f_dot = f_dot + jnp.einsum("tij,tj->ti", F[:, :, n:], d)
        c_dot = c_dot + jnp.einsum("tij,tj->ti", H[:, :, n:], d)
    # ok (every Q_uu positive definite) depends on the primal only. Where it fails the
    # recursion's K and k are NaN, and a batch that masks this problem out would still
    # meet them in the transpose (0 · NaN): the stand-in's Hessians are identities
    ok = riccati(F, jnp.zeros_like(f_dot), H, jnp.zeros_like(c_dot), HT,
                 jnp.zeros_like(cT_dot), free)[4]
    H = jnp.where(ok, H, jnp.eye(n + m, dtype=H.dtype))
    HT = jnp.where(ok, HT, jnp.eye(n, dtype=HT.dtype))
    K, k, *_ = riccati(F, f_dot, H, c_dot, HT, cT_dot, free)
    wx, wu = policy_rollout(F, f_dot, K, k, x0_dot)
    return (wx, wu + d), ok


# ----------------------------------------------------------------------------------
# Module
# ----------------------------------------------------------------------------------
def _bound_field(x: Any) -> Any:
    """Python-number limits as arrays, so that they are traced (not static) under jit."""
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        return jnp.asarray(float(x))
    return x


class MPC(eqx.Module):
    """Model-predictive controller over ``horizon`` steps.

    ``MPC(system, cost, horizon, u_lower=None, u_upper=None, max_iter=50, tol=None,
    gradient="implicit", solver="auto")``; ``mpc(x0, u_init=None, t0=0) → MPCSolution``.
    ``x0`` (n,) or batched (..., n) (vmapped; ``u_init`` (T, m) or (..., T, m)); ``t0``
    the time step of ``x0``: the problem covers steps ``t0 … t0 + T − 1`` of an LTV
    system, a time-varying cost or a ``System`` whose dynamics read ``t``.
    Control limits (m,) or (T, m) are enforced exactly (never ignored). Differentiable
    w.r.t. the arrays of ``system``, ``cost`` and ``x0`` (see the module docstring)."""

    system: System
    cost: Cost
    horizon: int = count_field("horizon")
    u_lower: Array | None = eqx.field(default=None, converter=_bound_field)
    u_upper: Array | None = eqx.field(default=None, converter=_bound_field)
    max_iter: int = eqx.field(static=True, default=50)
    tol: float | None = eqx.field(static=True, default=None)
    gradient: str = eqx.field(static=True, default="implicit")
    solver: str = eqx.field(static=True, default="auto")
    box_iters: int = count_field("box_iters", default=20)

    def __check_init__(self) -> None:
        if self.gradient not in GRADIENTS:
            raise ValueError(f"gradient: expected one of {GRADIENTS}, got {self.gradient!r}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver: expected one of {SOLVERS}, got {self.solver!r}")
        if not isinstance(self.system, System):
            raise TypeError(
                f"system: expected a jaxpose.dynamics.System, got {type(self.system).__name__}"
            )
        if not isinstance(self.cost, Cost):
            raise TypeError(
                f"cost: expected a jaxpose.control.Cost, got {type(self.cost).__name__}"
            )
        if isinstance(self.cost, QuadraticCost) and isinstance(self.system, (LTI, LTV)):
            lq_problem(self.system, self.cost, self.horizon)  # shape checks
        elif isinstance(self.system, LTV):
            self.system.matrices(self.horizon)  # its time steps cover the horizon

    def _m(self, x0: Array, u_init: Any) -> int:
        if u_init is not None:
            return int(jnp.shape(u_init)[-1])
        if isinstance(self.system, (LTI, LTV)):
            return self.system.input_dim
        if isinstance(self.cost, QuadraticCost):
            return self.cost.size - x0.shape[-1]
        for b in (self.u_lower, self.u_upper):
            if b is not None and jnp.ndim(b) >= 1:
                return int(jnp.shape(b)[-1])
        raise ValueError("u_init: needed to know the input size m for this system/cost")

    def __call__(self, x0: Any, u_init: Any = None, t0: Any = 0) -> MPCSolution:
        """Solve the horizon-``T`` problem from ``x0`` (n,) or a batch (…, n) (vmapped) at
        time step ``t0`` (an int ≥ 0, or an integer scalar array; traced under ``jit``, so
        a new start does not recompile).

        ``u_init`` (T, m) or (…, T, m) warm-starts the controls (zeros by default). Returns an
        :class:`MPCSolution` whose ``u[0]`` is the control to apply. Steps ``t0 … t0 + T − 1``
        outside an LTV system's or a time-varying cost's steps raise (``ValueError``, or
        ``eqx.error_if`` for a traced ``t0``).

        Checks run eagerly here; the solve is compiled with ``eqx.filter_jit`` (new arrays
        of the same shapes, in ``x0``, ``u_init`` or the module, reuse the program).
        """
        x0 = as_array(x0, "x0")
        if x0.ndim == 0:
            raise ValueError("x0: expected a state (n,) or a batch (..., n), got a scalar")
        n = x0.shape[-1]
        if isinstance(self.system, (LTI, LTV)) and self.system.state_dim != n:
            raise ValueError(
                f"x0: expected last dimension {self.system.state_dim} "
                f"(A is {self.system.state_dim}×{self.system.state_dim}), "
                f"got shape {tuple(x0.shape)}"
            )
        T, m = self.horizon, self._m(x0, u_init)
        if u_init is None:
            u_init = jnp.zeros((T, m), x0.dtype)
        u_init = as_array(u_init, "u_init")
        if u_init.ndim < 2 or u_init.shape[-2:] != (T, m):
            raise ValueError(
                f"u_init: expected shape (..., {T}, {m}) (horizon, inputs), got "
                f"{tuple(u_init.shape)}"
            )
        bounds = _bounds(self.u_lower, self.u_upper, T, m, x0.dtype)
        t0 = check_start_step(self.system, self.cost, T, t0)
        cfg = _Config(
            T, self.solver, self.max_iter, self.tol, self.gradient == "unroll", self.box_iters
        )
        return _mpc_solve(self, x0, u_init, bounds, t0, cfg)

    def _solve_one(self, x0: Array, u_init: Array, bounds: Any, t0: Array,
                   cfg: _Config) -> MPCSolution:
        if self.gradient == "implicit":
            xs, us, status, it = _solve_implicit(
                (self.system, self.cost, x0), u_init, bounds, t0, cfg=cfg
            )
        else:
            xs, us, status, it = _solve(self.system, self.cost, x0, u_init, bounds, t0, cfg)
        cost = self.cost.total(xs, us, t0)
        ok = jnp.isfinite(cost) | (status != Results.CONVERGED)
        status = jnp.where(ok, status, Results.NON_FINITE)
        return MPCSolution(xs, us, cost, status.astype(jnp.int32), it)

    def control(self, x: Any, u_init: Any = None, t0: Any = 0
                ) -> tuple[Array, Array, MPCSolution]:
        """Receding-horizon step at time step ``t0``: ``(u_0, warm start for the next
        step, solution)``; the warm start is the solution's controls shifted by one (last
        one repeated)."""
        sol = self(x, u_init, t0)
        warm = jnp.concatenate([sol.u[..., 1:, :], sol.u[..., -1:, :]], -2)
        return sol.u[..., 0, :], warm, sol


@eqx.filter_jit
@full_precision
def _mpc_solve(mpc: MPC, x0: Array, u_init: Array, bounds: Any, t0: Array,
               cfg: _Config) -> MPCSolution:
    """The compiled part of :meth:`MPC.__call__` (arguments already checked; ``t0`` an
    int32 scalar array, traced)."""
    n, (T, m) = x0.shape[-1], u_init.shape[-2:]
    batch = np.broadcast_shapes(x0.shape[:-1], u_init.shape[:-2])
    one = lambda x, u: mpc._solve_one(x, u, bounds, t0, cfg)  # noqa: E731
    if not batch:
        return one(x0, u_init)
    xb = jnp.broadcast_to(x0, (*batch, n)).reshape(-1, n)
    if u_init.ndim == 2:
        out = jax.vmap(lambda x: one(x, u_init))(xb)
    else:
        ub = jnp.broadcast_to(u_init, (*batch, T, m)).reshape(-1, T, m)
        out = jax.vmap(one)(xb, ub)
    return jax.tree.map(lambda a: a.reshape(*batch, *a.shape[1:]), out)


@eqx.filter_jit
@full_precision
def closed_loop(
    mpc: MPC, plant: System, x0: Any, steps: int, u_init: Any = None
) -> tuple[Array, Array, Array]:
    """Simulate ``plant`` for ``steps`` steps under receding-horizon ``mpc`` with warm
    starts (``lax.scan``). Returns ``xs`` (steps+1, n), ``us`` (steps, m) and the
    per-step solver ``status`` (steps,). Compiled with ``eqx.filter_jit`` (``steps``
    static). At step t, ``mpc`` solves over steps t … t + T − 1 (``MPC.__call__``'s
    ``t0``) and the plant advances at step t: an LTV model or time-varying cost of k
    steps needs k ≥ steps − 1 + T (else a ``ValueError`` naming ``steps``)."""
    if not isinstance(mpc, MPC):
        raise TypeError(
            f"closed_loop(mpc): expected a jaxpose.control.MPC, got {type(mpc).__name__}")
    if not isinstance(plant, System):
        raise TypeError(
            f"closed_loop(plant): expected a jaxpose.dynamics.System, got {type(plant).__name__}")
    steps = check_count(steps, "steps")
    x0 = as_array(x0, "x0", 1)
    T, m = mpc.horizon, mpc._m(x0, u_init)
    for k, what in time_varying_steps(mpc.system, mpc.cost):
        if steps - 1 + T > k:
            raise ValueError(
                f"steps: expected at most {k - T + 1}, got {steps}: the MPC solve at the "
                f"last step covers steps {steps - 1} … {steps + T - 2}, past the MPC's "
                f"{what} {k} time steps")
    u_init = jnp.zeros((T, m), x0.dtype) if u_init is None else as_array(u_init, "u_init", 2)

    def step(carry: tuple[Array, Array], t: Array):
        x, warm = carry
        u0, warm, sol = mpc.control(x, warm, t)
        x_next = plant.state_transition(x, u0, t)
        return (x_next, warm), (x_next, u0, sol.status)

    _, (xs, us, status) = jax.lax.scan(step, (x0, u_init), jnp.arange(steps))
    return jnp.concatenate([x0[None], xs], 0), us, status
