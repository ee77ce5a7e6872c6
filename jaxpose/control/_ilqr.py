"""Iterative LQR (Li & Todorov 2004; Tassa et al. 2012/2014) for nonlinear systems.

Each iteration linearises the dynamics (per-step ``jacfwd``) and quadratises the cost
along the nominal trajectory, runs the Riccati backward pass in deviation coordinates
with Levenberg–Marquardt regularisation μ on Q_uu, and a forward pass with a parallel
line search over step sizes α (first α whose actual decrease exceeds a fraction of the
predicted one). Box control limits are honoured exactly: the backward pass solves each
step's control-limited QP by projected Newton (control-limited DDP, as in Amos et al.
2018's differentiable MPC) and the forward pass clips to the box.

The loop is a ``lax.while_loop`` (stops at convergence): forward-mode derivatives (``jvp``,
``jacfwd``) of the iterates pass through it, reverse mode raises naming the alternatives;
``unroll=True`` runs exactly ``max_iter`` iterations in ``lax.scan`` so reverse-mode
gradients flow through the solver. Results carry a :class:`~jaxpose.Results` status.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_count
from .._forward_only import forward_mode_only
from .._precision import full_precision
from ..dynamics._checks import as_array
from ..dynamics._system import LTI, LTV, System
from ..results import Results
from ._boxqp import checked_box
from ._cost import Cost, QuadraticCost
from ._lqr import backward_step, check_quadratic_cost, check_start_step

Array = jax.Array

DEFAULT_ALPHAS = tuple(float(0.5**i) for i in range(10))
_ARMIJO = 1e-4
_REVERSE_MODE = (
    "ilqr(unroll=False): reverse-mode derivatives (grad, jacrev, vjp) cannot pass through "
    "its lax.while_loop. Use unroll=True (reverse mode through max_iter iterations), "
    "MPC(..., gradient='implicit') (the derivative of the optimum), or forward mode "
    "(jax.jvp, jax.jacfwd).")


class ILQRSolution(eqx.Module):
    """``x`` (T+1, n), ``u`` (T, m), ``cost``, feedback ``K`` (T, m, n), ``k`` (T, m)
    from the last backward pass, ``iterations``, ``status`` (a :class:`~jaxpose.Results`
    code: CONVERGED 0, MAX_STEPS 1 (``max_iter`` ran out), DIVERGED 2 (stalled at the
    regularisation limit or no descent), NON_FINITE 3) and the final regularisation ``reg``."""

    x: Array
    u: Array
    cost: Array
    K: Array
    k: Array
    iterations: Array
    status: Array
    reg: Array

    @property
    def status_name(self) -> Any:
        """``status`` as text (``"converged"``, ...; an array of names when batched), by
        :meth:`jaxpose.Results.name_of`."""
        return Results.name_of(self.status)


def _default_tol(dtype: Any) -> float:
    """Relative cost-decrease tolerance: 1e-10 (float64), 1e-5 (float32)."""
    return 1e-10 if jnp.finfo(dtype).bits >= 64 else 1e-5


def _dynamics_jacobians(system: System, xs: Array, us: Array, ts: Array) -> Array:
    """``F_t = [∂f/∂x, ∂f/∂u]`` (T, n, n+m) along a trajectory (per step ``jacfwd``)."""
    if isinstance(system, LTI):
        F = jnp.concatenate([system.A, system.B], -1)
        return jnp.broadcast_to(F, (us.shape[0], *F.shape))
    if isinstance(system, LTV):
        t = ts.astype(jnp.int32)
        return jnp.concatenate([system.A[t], system.B[t]], -1)

    def jac(x: Array, u: Array, t: Array) -> Array:
        A, B = jax.jacfwd(system.state_transition, argnums=(0, 1))(x, u, t)
        return jnp.concatenate([A, B], -1)

    return jax.vmap(jac)(xs, us, ts)


def _bounds(lower: Any, upper: Any, T: int, m: int, dtype: Any) -> tuple[Array, Array] | None:
    if lower is None and upper is None:
        return None
    lo = jnp.full((T, m), -jnp.inf, dtype) if lower is None else as_array(lower, "u_lower")
    hi = jnp.full((T, m), jnp.inf, dtype) if upper is None else as_array(upper, "u_upper")
    for arr, nm in ((lo, "u_lower"), (hi, "u_upper")):
        try:  # broadcasting to (T, m) itself: a (3,) limit must not widen m = 1 to 3
            ok = np.broadcast_shapes(arr.shape, (T, m)) == (T, m)
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(
                f"{nm}: expected a shape broadcastable to ({T}, {m}) "
                f"(horizon, inputs): a scalar, ({m},) or ({T}, {m}), got {tuple(arr.shape)}"
            )
    lo = jnp.broadcast_to(lo, (T, m)).astype(dtype)
    hi = jnp.broadcast_to(hi, (T, m)).astype(dtype)
    # traced limits (MPC's are differentiable fields) are checked under jit as well
    return checked_box(lo, hi, "u_lower", "u_upper")


def ilqr(
    system: System,
    cost: Cost,
    x0: Any,
    u_init: Any,
    *,
    u_lower: Any = None,
    u_upper: Any = None,
    max_iter: int = 50,
    tol: float | None = None,
    reg_init: float = 0.0,
    reg_min: float = 1e-6,
    reg_max: float = 1e10,
    reg_factor: float = 10.0,
    alphas: tuple[float, ...] = DEFAULT_ALPHAS,
    box_iters: int = 20,
    unroll: bool = False,
    t0: Any = 0,
) -> ILQRSolution:
    """Solve ``min Σ_t cost.stage(x_t, u_t, t) + cost.terminal(x_T)`` subject to
    ``x_{t+1} = system.state_transition(x_t, u_t, t)``, ``x_0 = x0``, and
    ``u_lower ≤ u_t ≤ u_upper`` (each optional; (m,) or (T, m)).

    ``x0`` (n,), ``u_init`` (T, m) (sets the horizon T; clipped to the box). For
    batches use ``jax.vmap``. ``max_iter`` may be a traced integer unless ``unroll``.
    ``tol``: relative cost decrease at which to stop (default 1e-10 for float64, 1e-5 for float32).
    ``t0``: the step of ``x0``; a time-varying cost or LTV system must have the steps
    ``t0 … t0 + T − 1`` (else a ``ValueError``, or ``eqx.error_if`` for a traced ``t0``).

    Argument checks run here (eagerly: NaN or crossed box limits raise); the solve is
    compiled with ``eqx.filter_jit`` (Python numbers and ``unroll``/``alphas`` static,
    arrays traced), so new arrays of the same shapes reuse the compiled program."""
    x0 = as_array(x0, "x0", 1)
    u_init = as_array(u_init, "u_init", 2)
    if isinstance(max_iter, int):
        if max_iter < 1:
            raise ValueError(f"max_iter: expected a positive int, got {max_iter!r}")
    elif unroll or not (hasattr(max_iter, "dtype") and jnp.issubdtype(max_iter.dtype, jnp.integer)):
        raise ValueError(
            f"max_iter: expected a positive int (an integer array is accepted without "
            f"unroll), got {max_iter!r}"
        )
    check_count(box_iters, "box_iters")
    T, m = u_init.shape
    dtype = jnp.result_type(x0.dtype, u_init.dtype)
    x0, u_init = x0.astype(dtype), u_init.astype(dtype)
    tol = _default_tol(dtype) if tol is None else float(tol)
    box = _bounds(u_lower, u_upper, T, m, dtype)
    t0 = check_start_step(system, cost, T, t0)
    # t0 traced (a new start time must not recompile); the options static or traced as given
    return _ilqr(system, cost, x0, u_init, box, max_iter, tol, reg_init, reg_min, reg_max,
                 reg_factor, alphas, box_iters, unroll, t0)


@eqx.filter_jit
@full_precision
def _ilqr(
    system: System,
    cost: Cost,
    x0: Array,
    u_init: Array,
    box: tuple[Array, Array] | None,
    max_iter: int | Array,
    tol: float,
    reg_init: float,
    reg_min: float,
    reg_max: float,
    reg_factor: float,
    alphas: tuple[float, ...],
    box_iters: int,
    unroll: bool,
    t0: Array,
) -> ILQRSolution:
    """The compiled iLQR loop behind :func:`ilqr` (arguments already checked)."""
    T, m = u_init.shape
    n = x0.shape[0]
    dtype = x0.dtype
    if box is not None:
        u_init = jnp.clip(u_init, box[0], box[1])
    ts = t0 + jnp.arange(T)
    al = jnp.asarray(alphas, dtype)
    f = system.state_transition
    try:
        x_try = jax.eval_shape(f, x0, u_init[0], ts[0])
    except (ValueError, TypeError) as err:
        raise type(err)(
            f"x0, u_init: the system does not accept x0 {tuple(x0.shape)} with inputs "
            f"u_init[t] {tuple(u_init.shape[1:])} (u_init is (T, m)): {err}"
        ) from err
    if x_try.shape != (n,):
        raise ValueError(
            f"system: state_transition maps x0 {tuple(x0.shape)} to "
            f"{tuple(x_try.shape)}; expected ({n},)"
        )
    # as lqr/MPC: Q's size, QT/pT shapes, time-varying steps covering the horizon
    if isinstance(cost, QuadraticCost):
        check_quadratic_cost(cost, n, m, T, "n = x0.shape[0], m = u_init.shape[1]")
    if isinstance(system, LTV):
        system.matrices(T)

    def simulate(us: Array) -> tuple[Array, Array]:
        def step(x: Array, inp: tuple[Array, Array]):
            u, t = inp
            xn = f(x, u, t)
            return xn, (xn, cost.stage(x, u, t))

        xT, (xs, cs) = jax.lax.scan(step, x0, (us, ts))
        xs = jnp.concatenate([x0[None], xs], 0)
        return xs, jnp.sum(cs) + cost.terminal(xT)

    def policy(xs: Array, us: Array, K: Array, k: Array, alpha: Array) -> tuple[Array, ...]:
        def step(x: Array, inp: tuple[Array, ...]):
            xb, ub, Kt, kt, t, lo, hi = inp
            u = ub + alpha * kt + Kt @ (x - xb)
            if box is not None:
                u = jnp.clip(u, lo, hi)
            xn = f(x, u, t)
            return xn, (xn, u, cost.stage(x, u, t))

        lo, hi = box if box is not None else (us, us)
        xT, (xn, un, cs) = jax.lax.scan(step, x0, (xs[:-1], us, K, k, ts, lo, hi))
        return jnp.concatenate([x0[None], xn], 0), un, jnp.sum(cs) + cost.terminal(xT)

    def backward(xs: Array, us: Array, mu: Array, k_warm: Array):
        F = _dynamics_jacobians(system, xs[:-1], us, ts)
        H, g = jax.vmap(cost.quadratize)(xs[:-1], us, ts)
        HT, gT = cost.quadratize_terminal(xs[-1])
        zero_f = jnp.zeros((n,), dtype)

        def step(carry: tuple[Array, Array], inp: tuple[Array, ...]):
            V, v = carry
            Ft, Ht, gt, ub, kw, lo, hi = inp
            bx = None if box is None else (lo - ub, hi - ub, kw)
            o = backward_step(
                V,
                v,
                Ft,
                zero_f,
                Ht,
                gt,
                reg=mu,
                box=bx,
                box_iters=box_iters,
                unroll=unroll,
                safe=unroll,
            )
            return (o.V, o.v), (o.K, o.k, o.dj1, o.dj2, o.ok)

        lo, hi = box if box is not None else (us, us)
        _, (K, k, dj1, dj2, ok) = jax.lax.scan(
            step, (HT, gT), (F, H, g, us, k_warm, lo, hi), reverse=True
        )
        return K, k, jnp.sum(dj1), jnp.sum(dj2), jnp.all(ok)

    xs0, J0 = simulate(u_init)
    finite0 = jnp.isfinite(J0) & jnp.all(jnp.isfinite(xs0))
    zK = jnp.zeros((T, m, n), dtype)
    zk = jnp.zeros((T, m), dtype)
    init = dict(
        xs=xs0,
        us=u_init,
        J=J0,
        mu=jnp.asarray(reg_init, dtype),
        K=zK,
        k=zk,
        it=jnp.array(0),
        status=jnp.where(finite0, Results.MAX_STEPS, Results.NON_FINITE),
        done=~finite0,
    )

    def iteration(s: dict[str, Array]) -> dict[str, Array]:
        K, k, dj1, dj2, ok = backward(s["xs"], s["us"], s["mu"], s["k"])
        J = s["J"]
        thresh = tol * (1.0 + jnp.abs(J))
        predicted = -(al * dj1 + al**2 * dj2)  # ≥ 0 when Q_uu ≻ 0
        small = ok & (predicted[0] <= thresh)
        xs_a, us_a, J_a = jax.vmap(lambda a: policy(s["xs"], s["us"], K, k, a))(al)
        dec = J - J_a
        good = ok & jnp.isfinite(J_a) & (dec > _ARMIJO * predicted) & (dec > 0)
        good = good & jnp.all(jnp.isfinite(xs_a.reshape(al.shape[0], -1)), -1)
        accept = jnp.any(good)
        idx = jnp.argmax(good)
        # Near the optimum the predicted decrease is at round-off level and the measured
        # one is noise: take the full (Newton) step anyway — it squares the remaining
        # error of the controls, which matters for implicit gradients.
        full_ok = jnp.isfinite(J_a[0]) & jnp.all(jnp.isfinite(xs_a[0]))
        final_step = small & full_ok
        idx = jnp.where(final_step, 0, idx)
        accept = accept | final_step
        xs_n = jnp.where(accept, xs_a[idx], s["xs"])
        us_n = jnp.where(accept, us_a[idx], s["us"])
        J_n = jnp.where(accept, J_a[idx], J)
        # A tiny decrease only counts as convergence after a full step (a short step can
        # make little progress far from the optimum).
        converged = small | (accept & (idx == 0) & (dec[idx] <= thresh))
        mu_up = jnp.maximum(s["mu"] * reg_factor, reg_min)
        mu_down = jnp.where(s["mu"] / reg_factor < reg_min, 0.0, s["mu"] / reg_factor)
        mu_n = jnp.where(accept | small, mu_down, mu_up)
        stalled = ~accept & ~small & (mu_n > reg_max)
        status = jnp.where(converged, Results.CONVERGED,
                           jnp.where(stalled, Results.DIVERGED, s["status"]))
        keep_k = ok & jnp.all(jnp.isfinite(k))
        return dict(
            xs=xs_n,
            us=us_n,
            J=J_n,
            mu=mu_n,
            K=jnp.where(keep_k, K, s["K"]),
            k=jnp.where(keep_k, k, s["k"]),
            it=s["it"] + 1,
            status=status,
            done=converged | stalled,
        )

    if unroll:

        def scan_body(s: dict[str, Array], _: None):
            new = iteration(s)
            out = jax.tree.map(lambda a, b: jnp.where(s["done"], a, b), s, new)
            return out, None

        final, _ = jax.lax.scan(scan_body, init, None, length=max_iter)
    else:
        final = jax.lax.while_loop(lambda s: ~s["done"] & (s["it"] < max_iter), iteration, init)
        final = forward_mode_only(final, _REVERSE_MODE)
    finite = jnp.isfinite(final["J"]) & jnp.all(jnp.isfinite(final["xs"]))
    status = jnp.where(finite, final["status"], Results.NON_FINITE).astype(jnp.int32)
    return ILQRSolution(
        final["xs"],
        final["us"],
        final["J"],
        final["K"],
        final["k"],
        final["it"],
        status,
        final["mu"],
    )
