"""Shared pieces of the filters: result type, covariance and measurement checks, Gaussian
helpers (a positive-semi-definite square root, scale-safe likelihoods and innovation tests)."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve

from ..dynamics._checks import as_array, check_psd, psd_checked
from ..dynamics._system import System
from ..dynamics._tangent import tangent_space
from ..lie._base import runtime_check

Array = jax.Array


class FilterResult(eqx.Module):
    """Per-step posterior estimates of a run: ``x`` (N, …) (stacked states or group
    elements), ``P`` (N, k, k) covariances in the state's tangent coordinates, and
    ``ok`` (N,) False where the step produced non-finite values or (``skip_nonfinite=True``)
    skipped its measurement."""

    x: Any
    P: Array
    ok: Array


def model_and_noise(model: Any, Q: Any, R: Any) -> tuple[System, Array, Array]:
    """A filter's validated ``(model, Q, R)``: a :class:`~jaxpose.dynamics.System` and the
    noise as :func:`noise_checked` gives it."""
    if not isinstance(model, System):
        raise TypeError(f"model: expected a jaxpose.dynamics.System, got {type(model).__name__}")
    return (model, *noise_checked(Q, R, once=True))


def noise_checked(Q: Any, R: Any, *, once: bool) -> tuple[Array, Array]:
    """A filter's process noise Q (n, n) positive semi-definite and measurement noise R
    (p, p) positive definite, as arrays, checked where their values are known; with
    ``once`` (construction, a whole run) also in the compiled program where they are
    traced, not at every step."""
    if once:
        return (psd_checked(as_array(Q, "Q", 2), "Q"),
                psd_checked(as_array(R, "R", 2), "R", strict=True))
    check_psd(Q, "Q")
    check_psd(R, "R", strict=True)
    return Q, R


def check_cov(P: Any, dim: int, name: str = "P", *, once: bool = False) -> Array:
    """A (dim, dim) covariance for a state with ``dim`` tangent coordinates; its values
    are checked where known, and also under ``jit`` with ``once`` (a starting covariance,
    not a per-step one: :func:`~jaxpose.dynamics._checks.psd_checked`)."""
    P = as_array(P, name, 2)
    if P.shape != (dim, dim):
        raise ValueError(
            f"{name}: expected shape ({dim}, {dim}) (state tangent size), got {tuple(P.shape)}"
        )
    if once:
        return psd_checked(P, name)
    check_psd(P, name)
    return P


def as_state(x: Any, name: str = "x") -> Any:
    """An array state as a floating array (integers promoted, as every array argument;
    autodiff linearisation needs floats); group elements and other pytrees unchanged."""
    if isinstance(x, (jax.Array, float, int)) or (
        hasattr(x, "__array__") and not isinstance(x, eqx.Module)
    ):
        return as_array(x, name)
    return x


def check_noise_dim(M: Array, dim: int, name: str, what: str) -> None:
    """``M`` must be (dim, dim); the error names ``name`` and what ``dim`` is."""
    if jnp.shape(M) != (dim, dim):
        raise ValueError(
            f"{name}: expected shape ({dim}, {dim}) ({what}), got {tuple(jnp.shape(M))}"
        )


def symmetrize(P: Array) -> Array:
    return 0.5 * (P + P.T)


def finite_tree(*trees: Any) -> Array:
    leaves = [leaf for t in trees for leaf in jax.tree.leaves(t)]
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in leaves]))


def kalman_gain(PHt: Array, S: Array) -> tuple[Array, Array]:
    """``K = PHᵀ S⁻¹`` by Cholesky of S; also returns the factor."""
    L = jnp.linalg.cholesky(symmetrize(S))
    K = cho_solve((L, True), PHt.T).T
    return K, L


def psd_cholesky(A: Array) -> Array:
    """Lower-triangular ``L`` with ``L Lᵀ = A`` for a symmetric positive *semi*-definite
    ``A`` (k, k): a Cholesky factorisation whose pivots at or below ``k·eps·max(diag A)``
    (rounding level) give a zero column instead of NaN.

    Chosen over an eigendecomposition with clipped eigenvalues because (i) for a
    positive-definite ``A`` it is the Cholesky factor (same operations, so the UKF's sigma
    points and results are unchanged there), and (ii) its derivatives stay finite where
    ``eigh``'s do not (repeated eigenvalues, e.g. ``P = σ²I``, make the ``eigh`` JVP
    divide by zero). Over a jitter ``A + δI`` it has the advantage of being exact for PSD
    input: null directions get no spread at all (``A = 0`` gives ``L = 0``). Non-finite
    entries propagate (NaN in, NaN out). ``k`` columns unrolled (a ``fori_loop`` for large
    ``k``); every branch is NaN-free under differentiation (double ``where``).
    """
    return _cholesky_columns(_differentiable_where_definite(symmetrize(A)))


@jax.custom_jvp
def _differentiable_where_definite(A: Array) -> Array:
    """Identity on ``A`` that raises when differentiated where :func:`psd_cholesky` gives
    a zero column: the factor's derivative there is not defined (the square root of a zero
    pivot), and its zero columns would silently give derivatives of 0 in those directions
    (a UKF differentiated at ``P = 0`` returned 0 where the true derivative is 1)."""
    return A


@_differentiable_where_definite.defjvp
def _definite_jvp(primals: tuple[Array], tangents: tuple[Array]) -> tuple[Array, Array]:
    (A,), (dA,) = primals, tangents
    # the check is on A (the point the factor's tangent is taken at), so it stays in a
    # reverse-mode program; a check on a factor computed here with jax.jvp would not
    # (nothing downstream uses that primal, and dead-code elimination drops it)
    singular = jnp.any(jnp.diagonal(_cholesky_columns(A)) == 0)
    A = runtime_check(A, singular, (
        "psd_cholesky: differentiating through a covariance that is singular (a zero "
        "variance direction, e.g. P = 0): the square-root factor has no derivative there "
        "and the result would be silently wrong; differentiate at a positive-definite P "
        "(add a small variance) or use the EKF"))
    return A, dA


def _cholesky_columns(A: Array) -> Array:
    """:func:`psd_cholesky` of a symmetric ``A``."""
    k = A.shape[-1]
    eps = jnp.finfo(A.dtype).eps
    tol = k * eps * jnp.maximum(jnp.max(jnp.diagonal(A)), 0.0)
    rows = jnp.arange(k)

    def column(j: Any, L: Array) -> Array:
        lj = L[j]  # row j: only its first j entries are set
        d = A[j, j] - lj @ lj
        pos = ~(d <= tol)  # NaN stays "positive" so that it propagates
        ljj = jnp.where(pos, jnp.sqrt(jnp.where(pos, d, 1.0)), 0.0)
        below = (A[:, j] - L @ lj) / jnp.where(pos, ljj, 1.0)
        col = jnp.where(rows > j, jnp.where(pos, below, 0.0), jnp.where(rows == j, ljj, 0.0))
        return L.at[:, j].set(col)

    L = jnp.zeros_like(A)
    if k <= 16:
        for j in range(k):
            L = column(j, L)
        return L
    return jax.lax.fori_loop(0, k, column, L)


def relative_loglik(r: Array, L_inv: Array) -> tuple[Array, Array]:
    """Gaussian log-likelihoods of innovations ``r`` (N, p) under ``N(0, S)``, ``S = L Lᵀ``
    (``L_inv`` = L⁻¹), up to one constant shared by all N: ``−½(‖z_i‖² − min_j ‖z_j‖²)``
    with ``z = L⁻¹ r``. Scale-safe: the squares are formed from ``z / max|z|``, so an
    innovation of 1e200 gives the nearest rows 0 and the others ``-inf`` (instead of
    ``inf − inf = NaN``). A row that is not finite (a particle whose observation is NaN)
    gets ``-inf`` and plays no part in the others' (it made every row NaN). Also returns
    ``min ‖z‖²`` over the finite rows (``inf`` when it overflows or none is finite)."""
    z = r @ L_inv.T
    finite = jnp.all(jnp.isfinite(z), -1)
    z = jnp.where(finite[:, None], z, 0.0)
    s = jnp.max(jnp.abs(z))
    s = jnp.where(jnp.isfinite(s) & (s > 0), s, 1.0)
    q = jnp.where(finite, jnp.sum(jnp.square(z / s), -1), jnp.inf)
    qmin = jnp.min(q)
    ll = jnp.where(finite, -0.5 * ((s * (q - qmin)) * s), -jnp.inf)
    return ll, (s * jnp.sqrt(qmin)) ** 2


def innovation_ok(L: Array, r: Array) -> Array:
    """True when the normalised innovation squared ``rᵀ S⁻¹ r`` (``S = L Lᵀ``) is finite:
    False for a non-finite ``r`` or one so large (beyond ~1e154 standard deviations in
    float64) that no information survives in floating point."""
    z = jax.scipy.linalg.solve_triangular(L, r, lower=True)
    return jnp.isfinite(z @ z)


def select_tree(pred: Array, a: Any, b: Any) -> Any:
    """``a`` where ``pred`` else ``b``, leaf by leaf (same structure)."""
    return jax.tree.map(lambda u, v: jnp.where(pred, u, v), a, b)


def _describe(tree: Any, batch: tuple = ()) -> str:
    shapes = [(*batch, *jnp.shape(leaf)) for leaf in jax.tree.leaves(tree)]
    if len(shapes) == 1 and not isinstance(tree, eqx.Module):
        return f"shape {shapes[0]}"
    return f"{type(tree).__name__} with leaf shapes {shapes}"


def check_measurement(y: Any, y_hat: Any, R: Array, name: str = "y", batch: tuple = ()) -> None:
    """Trace-time check that a measurement ``y`` (or a stack ``ys`` with leading ``batch``
    axes) matches the model's observation ``y_hat = h(x, u, t)`` and the noise ``R``."""
    dim = tangent_space(y_hat).dim
    want = jax.tree.map(lambda a: (*batch, *jnp.shape(a)), y_hat)
    ok = jax.tree.structure(y) == jax.tree.structure(y_hat) and all(
        tuple(jnp.shape(a)) == w
        for a, w in zip(jax.tree.leaves(y), jax.tree.leaves(want, is_leaf=_is_shape))
    )
    if not ok:
        what = "one measurement per step; " if batch else ""
        raise ValueError(
            f"{name}: expected {_describe(y_hat, batch)} ({what}h(x) gives {dim} values "
            f"and R is {R.shape[0]}×{R.shape[1]}), got {_describe(y)}"
        )


def _is_shape(v: Any) -> bool:
    return isinstance(v, tuple)


def check_sequence(model: Any, R: Array, x0: Any, ys: Any, us: Any, t0: Any) -> Array:
    """Trace-time checks of a run's inputs: ``us`` (N, m) with one row per measurement,
    ``R`` matching the model's observation size and ``ys`` (N, …) matching ``h(x0)``.
    Returns ``us`` as an array."""
    us = jnp.asarray(us)
    leaves = jax.tree.leaves(ys)
    if not leaves or any(jnp.ndim(a) == 0 for a in leaves):
        raise ValueError(f"ys: expected a stack of measurements (N, p), got {_describe(ys)}")
    n_y = jnp.shape(leaves[0])[0]
    if n_y == 0:
        raise ValueError(f"ys: expected at least one measurement (N ≥ 1), got {_describe(ys)}")
    if us.ndim != 2 or us.shape[0] != n_y:
        raise ValueError(
            f"us: expected shape ({n_y}, m) (one input per measurement), got {tuple(us.shape)}"
        )
    try:
        eqx.filter_eval_shape(model.state_transition, x0, us[0], jnp.asarray(t0))
        y_hat = model.observation(x0, us[0], jnp.asarray(t0))
    except (ValueError, TypeError) as err:
        raise type(err)(
            f"x0, us: the model does not accept the state x0 with inputs us[t] of shape "
            f"{tuple(us.shape[1:])} (us is (N, m)): {err}"
        ) from err
    dim = tangent_space(y_hat).dim
    check_noise_dim(R, dim, "R", f"measurement noise: h(x) gives {dim} values")
    check_measurement(ys, y_hat, R, "ys", (n_y,))
    return us
