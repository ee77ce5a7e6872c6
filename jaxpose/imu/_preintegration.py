"""On-manifold IMU preintegration (Forster et al., RSS 2015 / T-RO 2017).

Conventions (see ``docs/imu.md``):

* samples: ``gyro`` (…, N, 3) body angular rate [rad/s], ``acc`` (…, N, 3) body specific
  force [m/s²] (what an accelerometer measures: ``Rᵀ(a − g)``, so +9.81 up when at rest
  z-up), ``dt`` scalar, (N,) or (…, N) [s]. Sample k is held constant over its own
  ``dt[k]`` (zero-order hold, as in GTSAM and Forster et al.).
* biases are subtracted: ``ω = gyro − b_g``, ``a = acc − b_a``; the bias vector layout
  is ``[b_g, b_a]`` (GTSAM's ``ConstantBias.vector()`` is ``[b_a, b_g]``).
* deltas (gravity-free, in the body frame at the first sample)::

      ΔR = Π Exp(ω_k dt_k),  Δv = Σ ΔR_k a_k dt_k,  Δp = Σ Δv_k dt_k + ½ ΔR_k a_k dt_k²

* error state / covariance order ``[δφ, δv, δp]`` (Forster's chart: ``ΔR̃ = ΔR·Exp(δφ)``,
  ``Δṽ = Δv + δv``, ``Δp̃ = Δp + δp``); GTSAM's ``preintMeasCov`` is ordered
  ``[rot, pos, vel]`` and (for its manifold scheme) expresses δp, δv in the end frame.
* noise: continuous-time densities σ_g [rad/s/√Hz], σ_a [m/s²/√Hz] (discrete variance
  σ²/dt per sample, as GTSAM's ``gyroscopeCovariance``/``accelerometerCovariance``) and an
  optional integration noise σ_i adding ``σ_i²·dt`` to the position block.
* gravity only enters :func:`predict`: ``R_j = R_i ΔR``, ``v_j = v_i + g Δt + R_i Δv``,
  ``p_j = p_i + v_i Δt + ½ g Δt² + R_i Δp`` with ``g`` the gravity vector in the
  navigation frame (``[0, 0, −9.81]`` for z-up; GTSAM's ``MakeSharedU(9.81)``).

Computation (``jaxpose.imu._core``): the cumulative rotations are an associative prefix
product of quaternions (``lax.associative_scan`` on accelerators; on CPU a blocked
two-level scan, O(N) work and ~2√N sequential steps) and Δv, Δp cumulative sums; the
window's covariance and bias Jacobians are sums of every sample's noise mapped to the
window end by a closed-form gain (no sequential recurrence, one matrix product).
``prefix=True`` returns every cumulative delta; with covariance/Jacobians it scans the
associative composition of (ΔR, Δv, Δp, Δt, Σ, J) the same way.
``scheme="tangent"`` reproduces GTSAM's default ``PreintegratedImuMeasurements``
(first-order rotation update, sequential ``lax.scan``).
"""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import _small_linalg as small_linalg
from .._precision import full_precision
from ..lie import SO3
from ..lie import _quaternion as quat
from ..lie._base import runtime_check
from . import _core, _tangent
from ._checks import (
    as_float,
    biases,
    broadcast_samples,
    check_finite_inputs,
    check_outputs,
    check_samples,
    check_values,
    noise_sigma,
    raise_flagged,
    scalar_var,
)
from ._state import NavState

Array = jax.Array

SCHEMES = ("manifold", "tangent")
"""Preintegration schemes: ``"manifold"`` (Forster, associative scan) and ``"tangent"``
(GTSAM's default first-order scheme, sequential scan)."""


class Preintegrated(eqx.Module):
    """Preintegrated IMU measurements of one window (or a batch of windows).

    Fields (``*b`` = batch shape):
        rot: ΔR_ij as :class:`~jaxpose.lie.SO3` (*b).
        vel, pos: Δv_ij, Δp_ij (*b, 3), in the body frame at the window start.
        dt: Δt_ij (*b).
        cov: (*b, 9, 9) covariance of ``[δφ, δv, δp]``, or None.
        jac: (*b, 9, 6) ∂[φ, v, p]/∂[b_g, b_a] at the linearisation biases, or None.
        gyro_bias, acc_bias: (*b, 3) biases used for the preintegration (b̂_g, b̂_a).
    """

    rot: SO3
    vel: Array
    pos: Array
    dt: Array
    cov: Array | None
    jac: Array | None
    gyro_bias: Array
    acc_bias: Array

    # -- bias Jacobian blocks (Forster et al.'s notation) ------------------------------
    @property
    def d_rot_d_gyro_bias(self) -> Array:
        """∂ΔR/∂b_g (*b, 3, 3), right chart: ΔR(b̂ + δ) ≈ ΔR·Exp(J δ)."""
        return self._jac()[..., 0:3, 0:3]

    @property
    def d_vel_d_gyro_bias(self) -> Array:
        """∂Δv/∂b_g (*b, 3, 3): Δv(b̂ + δ) ≈ Δv + J δ."""
        return self._jac()[..., 3:6, 0:3]

    @property
    def d_vel_d_acc_bias(self) -> Array:
        """∂Δv/∂b_a (*b, 3, 3)."""
        return self._jac()[..., 3:6, 3:6]

    @property
    def d_pos_d_gyro_bias(self) -> Array:
        """∂Δp/∂b_g (*b, 3, 3): Δp(b̂ + δ) ≈ Δp + J δ."""
        return self._jac()[..., 6:9, 0:3]

    @property
    def d_pos_d_acc_bias(self) -> Array:
        """∂Δp/∂b_a (*b, 3, 3)."""
        return self._jac()[..., 6:9, 3:6]

    def _jac(self) -> Array:
        if self.jac is None:
            raise ValueError("Preintegrated: bias Jacobians were not computed "
                             "(preintegrate(..., bias_jacobians=True))")
        return self.jac

    @property
    def information(self) -> Array:
        """Inverse covariance (*b, 9, 9), symmetrised.

        A zero noise density (``gyro_noise=0`` or ``acc_noise=0``) gives a well-defined but
        singular covariance (zero variance in the directions it drives): the information is
        infinite there, so this raises (``eqx.error_if``, also under ``jit``) when the
        covariance is singular to working precision (smallest eigenvalue ≤ 9·eps·largest)
        instead of returning inf/NaN or rounding garbage. Use ``cov`` directly then."""
        if self.cov is None:
            raise ValueError("Preintegrated: no covariance (give gyro_noise/acc_noise)")
        cov = self.cov
        w = jnp.linalg.eigvalsh(cov)
        eps = jnp.finfo(cov.dtype).eps
        singular = ~(w[..., 0] > cov.shape[-1] * eps * w[..., -1])
        # written out, not LAPACK: a batched LAPACK inverse next to the batched eigvalsh
        # deadlocked XLA:CPU on 2 cores (5000 segments; jaxpose._small_linalg). NaN where
        # the factorisation fails in rounding (condition near 1/eps): raised as singular
        info = small_linalg.spd_inv(cov)
        singular = singular | ~jnp.all(jnp.isfinite(info), axis=(-2, -1))
        info = eqx.error_if(
            info, jnp.any(singular),
            "Preintegrated.information: the covariance is singular (a zero noise density "
            "makes the information infinite in the directions it drives); give positive "
            "gyro_noise and acc_noise, or use .cov")
        return 0.5 * (info + jnp.swapaxes(info, -1, -2))

    # -- first-order bias correction and prediction --------------------------------------
    def corrected(
        self, gyro_bias: Any = None, acc_bias: Any = None
    ) -> tuple[SO3, Array, Array]:
        """(ΔR, Δv, Δp) for new biases, to first order around the preintegration biases:
        ``ΔR·Exp(J_R^g δb_g)``, ``Δv + J_v^g δb_g + J_v^a δb_a``, ``Δp + J_p^g δb_g +
        J_p^a δb_a`` with ``δb = b − b̂``. ``None`` keeps b̂."""
        if gyro_bias is None and acc_bias is None:
            return self.rot, self.vel, self.pos
        dbg = _bias_delta(gyro_bias, self.gyro_bias, "corrected(gyro_bias)")
        dba = _bias_delta(acc_bias, self.acc_bias, "corrected(acc_bias)")
        db = jnp.concatenate(jnp.broadcast_arrays(dbg, dba), -1)
        d = jnp.einsum("...ij,...j->...i", self._jac(), db)
        rot = SO3(quat.multiply(self.rot.data, quat.exp(d[..., 0:3])))
        return rot, self.vel + d[..., 3:6], self.pos + d[..., 6:9]

    def predict(
        self, state: NavState, gravity: Any, gyro_bias: Any = None, acc_bias: Any = None
    ) -> NavState:
        """Navigation state at the window end from ``state`` at its start (see module
        docstring), with first-order bias correction when biases are given."""
        return predict(state, self, gravity, gyro_bias, acc_bias)

    def compose(self, other: Preintegrated) -> Preintegrated:
        """This window followed by ``other`` (same linearisation biases): deltas,
        covariance and bias Jacobians of the concatenated window."""
        if not isinstance(other, Preintegrated):
            raise TypeError(f"Preintegrated.compose(other): expected Preintegrated, got "
                            f"{type(other).__name__}")
        if (self.cov is None) != (other.cov is None) or (self.jac is None) != (
            other.jac is None
        ):
            raise ValueError("Preintegrated.compose(other): both windows need the same "
                             "outputs (covariance and bias Jacobians or neither)")
        differ = jnp.any(self.gyro_bias != other.gyro_bias) | jnp.any(
            self.acc_bias != other.acc_bias)
        out = runtime_check(
            _core.compose(_to_delta(self), _to_delta(other)), differ,
            "Preintegrated.compose(other): the windows were preintegrated at different "
            "linearisation biases (gyro_bias, acc_bias); preintegrate both at the same ones")
        return _from_delta(out, self.gyro_bias, self.acc_bias)

    __matmul__ = compose


def _to_delta(p: Preintegrated) -> _core.Delta:
    return _core.Delta(p.rot.data, p.vel, p.pos, p.dt, p.cov, p.jac)


def _from_delta(d: _core.Delta, bg: Array, ba: Array) -> Preintegrated:
    return Preintegrated(SO3(d.q), d.v, d.p, d.t, d.cov, d.jac, bg, ba)


def _bias_delta(b: Any, b_hat: Array, name: str) -> Array:
    if b is None:
        return jnp.zeros_like(b_hat)
    arr = as_float(b, name)
    if arr.ndim == 0 or arr.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape (..., 3), got {tuple(arr.shape)}")
    arr = runtime_check(arr, ~jnp.all(jnp.isfinite(arr)), f"{name}: expected finite values")
    return arr.astype(b_hat.dtype) - b_hat


def _vmap_n(fn: Any, n: int) -> Any:
    for _ in range(n):
        fn = jax.vmap(fn)
    return fn


# ----------------------------------------------------------------------------------
# Preintegration
# ----------------------------------------------------------------------------------
@full_precision
def preintegrate(
    gyro: Any,
    acc: Any,
    dt: Any,
    *,
    gyro_bias: Any = None,
    acc_bias: Any = None,
    gyro_noise: Any = None,
    acc_noise: Any = None,
    integration_noise: Any = 0.0,
    bias_jacobians: bool = True,
    prefix: bool = False,
    scheme: str = "manifold",
    check: bool = True,
) -> Preintegrated:
    """Preintegrate IMU samples between two keyframes.

    Args:
        gyro, acc: (…, N, 3) angular rates [rad/s] and specific forces [m/s²] (body).
        dt: scalar, (N,) or (…, N) sample durations [s], all > 0.
        gyro_bias, acc_bias: (3,) or (…, 3) linearisation biases b̂ (default 0).
        gyro_noise, acc_noise: σ_g [rad/s/√Hz], σ_a [m/s²/√Hz] (scalar or (3,)) noise
            densities; the covariance is computed when either is given (the other counts
            as 0).
        integration_noise: σ_i (scalar), GTSAM's integration covariance σ_i²·I.
        bias_jacobians: compute ∂[φ, v, p]/∂[b_g, b_a].
        prefix: return every cumulative delta (batch (…, N)) instead of the window's.
        scheme: ``"manifold"`` (Forster et al., exact rotation increments, associative)
            or ``"tangent"`` (GTSAM's default ``PreintegratedImuMeasurements``).
        check: run-time value checks: NaN/inf samples, biases or noise densities, dt ≤ 0,
            inf or NaN, and outputs that overflow although the inputs are finite (extreme
            magnitudes such as 1e200) raise: eagerly a one-line
            :class:`~jaxpose.lie.InvalidValueError`, under ``jit`` and ``vmap`` the same
            message through ``eqx.error_if``. With ``check=False`` bad values propagate as
            NaN/inf into the outputs.

    Returns:
        :class:`Preintegrated` with batch shape (…) (or (…, N) with ``prefix``).

    Shapes, types and options are checked here (Python exceptions naming the argument);
    the computation runs as one compiled function (cached per shape and options).
    """
    return _checked_preintegrate(
        "preintegrate", gyro, acc, dt, gyro_bias=gyro_bias, acc_bias=acc_bias,
        gyro_noise=gyro_noise, acc_noise=acc_noise, integration_noise=integration_noise,
        bias_jacobians=bias_jacobians, prefix=prefix, scheme=scheme, check=check)


def _checked_preintegrate(
    fn: str, gyro: Any, acc: Any, dt: Any, *, gyro_bias: Any = None, acc_bias: Any = None,
    gyro_noise: Any = None, acc_noise: Any = None, integration_noise: Any = 0.0,
    bias_jacobians: bool = True, prefix: bool = False, scheme: str = "manifold",
    check: bool = True,
) -> Preintegrated:
    """:func:`preintegrate`, its errors naming ``fn`` (the public function called)."""
    if scheme not in SCHEMES:
        raise ValueError(f"{fn}(scheme={scheme!r}): expected one of {SCHEMES}")
    g, a, d, batch, dtype = check_samples(gyro, acc, dt, fn)
    bg, ba, batch = biases(gyro_bias, acc_bias, batch, fn)
    gs = None if gyro_noise is None else noise_sigma(gyro_noise, f"{fn}(gyro_noise)", dtype)
    as_ = None if acc_noise is None else noise_sigma(acc_noise, f"{fn}(acc_noise)", dtype)
    iv = scalar_var(integration_noise, f"{fn}(integration_noise)", dtype)
    # eager call: the checks come back as flags and raise a one-line InvalidValueError
    # here (eqx.error_if inside jax.jit would surface as a JaxRuntimeError dump)
    inputs = (g, a, d, bg, ba, gs, as_, iv)
    eager = bool(check) and not any(isinstance(x, jax.core.Tracer) for x in inputs)
    out, flags = _preintegrate(*inputs, fn=fn, batch=batch, dtype=jnp.dtype(dtype),
                               bias_jacobians=bool(bias_jacobians), prefix=bool(prefix),
                               scheme=scheme, check=bool(check), eager=eager)
    if eager:
        raise_flagged(flags, fn)
    return out


@functools.partial(jax.jit, static_argnames=("fn", "batch", "dtype", "bias_jacobians",
                                             "prefix", "scheme", "check", "eager"))
def _preintegrate(
    g: Array, a: Array, d: Array, bg: Array | None, ba: Array | None, gs: Array | None,
    as_: Array | None, iv: Array, *, fn: str, batch: tuple[int, ...], dtype: Any,
    bias_jacobians: bool, prefix: bool, scheme: str, check: bool, eager: bool,
) -> tuple[Preintegrated, dict[str, Array]]:
    """The preintegration and ``check``'s flags: with ``eager`` the failed checks are
    returned as ``{name: bool}`` (see ``_checks.raise_flagged``), else ``eqx.error_if``;
    messages name ``fn``."""
    flags: dict[str, Array] | None = {} if eager else None
    g, a, d = broadcast_samples(g, a, d, batch, dtype)
    zero = jnp.zeros(3, dtype)
    bg = jnp.broadcast_to(zero if bg is None else bg.astype(dtype), (*batch, 3))
    ba = jnp.broadcast_to(zero if ba is None else ba.astype(dtype), (*batch, 3))
    if check:
        g, a, d = check_values(g, a, d, fn, flags)
        c = check_finite_inputs({"gyro_bias": bg, "acc_bias": ba, "gyro_noise": gs,
                                 "acc_noise": as_, "integration_noise": iv}, fn, flags)
        bg, ba, gs, as_, iv = (c["gyro_bias"], c["acc_bias"], c["gyro_noise"],
                               c["acc_noise"], c["integration_noise"])
    # keeps XLA from constant-folding cumulative sums of a constant dt (slow compiles)
    d = jax.lax.optimization_barrier(d)
    noise = None
    if gs is not None or as_ is not None:
        noise = _core.Noise(zero if gs is None else gs * gs, zero if as_ is None else as_ * as_, iv)

    def one(g1: Array, a1: Array, d1: Array, bg1: Array, ba1: Array) -> _core.Delta:
        w, f = g1 - bg1, a1 - ba1
        if scheme == "tangent":
            return _tangent.preintegrate(w, f, d1, noise, bias_jacobians, prefix)
        if not prefix:
            return _core.window(w, f, d1, noise, bias_jacobians)
        if noise is None and not bias_jacobians:
            q, v, p, t, _, _ = _core.prefix_values(w, f, d1)
            return _core.Delta(q, v, p, t, None, None)
        return _core.prefix(_core.samples(w, f, d1, noise, bias_jacobians))

    out = _vmap_n(one, len(batch))(g, a, d, bg, ba)
    if check:
        out = check_outputs(out, fn, flags)
    if prefix:
        n = g.shape[-2]
        bg = jnp.broadcast_to(bg[..., None, :], (*batch, n, 3))
        ba = jnp.broadcast_to(ba[..., None, :], (*batch, n, 3))
    return _from_delta(out, bg, ba), flags or {}


def predict(
    state: NavState,
    pre: Preintegrated,
    gravity: Any,
    gyro_bias: Any = None,
    acc_bias: Any = None,
) -> NavState:
    """``R_j = R_i ΔR``, ``v_j = v_i + g Δt + R_i Δv``, ``p_j = p_i + v_i Δt + ½ g Δt² +
    R_i Δp`` (deltas bias-corrected to first order when biases are given); broadcasts.
    The result has the dtype of ``state`` and ``pre`` (gravity and biases are cast to it:
    a list gravity made float32 data float64); non-finite gravity or biases raise."""
    if not isinstance(state, NavState):
        raise TypeError(f"predict(state): expected NavState, got {type(state).__name__}")
    if not isinstance(pre, Preintegrated):
        raise TypeError(f"predict(pre): expected Preintegrated, got {type(pre).__name__}")
    g = as_float(gravity, "predict(gravity)")
    if g.shape[-1:] != (3,):
        raise ValueError(f"predict(gravity): expected a 3-vector in the navigation frame, "
                         f"got shape {tuple(g.shape)}")
    g = runtime_check(g, ~jnp.all(jnp.isfinite(g)), "predict(gravity): expected finite values")
    g = g.astype(jnp.result_type(state.vel, state.pos, pre.vel))
    drot, dv, dp = pre.corrected(gyro_bias, acc_bias)
    t = pre.dt[..., None]
    q = state.rot.data
    rot = SO3(quat.multiply(q, drot.data))
    vel = state.vel + g * t + quat.rotate(q, dv)
    pos = state.pos + state.vel * t + 0.5 * g * t * t + quat.rotate(q, dp)
    batch = jnp.broadcast_shapes(rot.shape, vel.shape[:-1], pos.shape[:-1])  # e.g. a batch
    return NavState(SO3(jnp.broadcast_to(rot.data, (*batch, 4))),  # of gravities alone
                    jnp.broadcast_to(vel, (*batch, 3)), jnp.broadcast_to(pos, (*batch, 3)))


@full_precision
def dead_reckon(
    gyro: Any,
    acc: Any,
    dt: Any,
    gravity: Any,
    init: NavState | None = None,
    *,
    gyro_bias: Any = None,
    acc_bias: Any = None,
    scheme: str = "manifold",
    check: bool = True,
) -> NavState:
    """Dead reckoning: the navigation state after every sample, (…, N) batch.

    ``init`` (default: identity rotation, zero velocity and position) is the state before
    the first sample; the states come from the cumulative deltas (``associative_scan``)
    and :func:`predict`, so they equal sequential strapdown integration to rounding."""
    pre = _checked_preintegrate("dead_reckon", gyro, acc, dt, gyro_bias=gyro_bias,
                                acc_bias=acc_bias, bias_jacobians=False, prefix=True,
                                scheme=scheme, check=check)
    if init is None:
        init = NavState.identity(dtype=pre.vel.dtype)
    if not isinstance(init, NavState):
        raise TypeError(f"dead_reckon(init): expected NavState or None, got "
                        f"{type(init).__name__}")
    expand = jax.tree.map(lambda x: x[..., None, :], init)
    return predict(expand, pre, gravity)


class ImuPreintegrator(eqx.Module):
    """IMU model: noise densities, gravity and scheme; calls :func:`preintegrate`.

    Fields are arrays (differentiable): ``gyro_noise``, ``acc_noise`` (3,) densities σ,
    ``integration_noise`` () σ_i, ``gravity`` (3,) in the navigation frame. ``scheme``
    is static. Defaults: GTSAM ``ImuFactorsExample`` noise, z-up gravity 9.81.
    """

    gyro_noise: Array
    acc_noise: Array
    integration_noise: Array
    gravity: Array
    scheme: str = eqx.field(static=True)

    def __init__(
        self,
        gyro_noise: Any = 2.05689024915e-4,
        acc_noise: Any = 3.924e-4,
        integration_noise: Any = 0.0,
        gravity: Any = (0.0, 0.0, -9.81),
        scheme: str = "manifold",
    ):
        if scheme not in SCHEMES:
            raise ValueError(f"ImuPreintegrator(scheme={scheme!r}): expected one of {SCHEMES}")
        for name, x in (("gyro_noise", gyro_noise), ("acc_noise", acc_noise)):
            arr = as_float(x, f"ImuPreintegrator({name})")
            setattr(self, name, noise_sigma(arr, f"ImuPreintegrator({name})", arr.dtype))
        self.integration_noise = as_float(integration_noise,
                                           "ImuPreintegrator(integration_noise)")
        if self.integration_noise.ndim != 0:
            raise ValueError(f"ImuPreintegrator(integration_noise): expected a scalar σ, got "
                             f"shape {tuple(self.integration_noise.shape)}")
        g = as_float(gravity, "ImuPreintegrator(gravity)")
        if g.shape != (3,):
            raise ValueError(f"ImuPreintegrator(gravity): expected a 3-vector, got shape "
                             f"{tuple(g.shape)}")
        self.gravity = g
        self.scheme = scheme

    def __call__(
        self, gyro: Any, acc: Any, dt: Any, gyro_bias: Any = None, acc_bias: Any = None,
        *, prefix: bool = False, check: bool = True,
    ) -> Preintegrated:
        """Preintegrated deltas, covariance and bias Jacobians of (…, N) samples."""
        return preintegrate(
            gyro, acc, dt, gyro_bias=gyro_bias, acc_bias=acc_bias,
            gyro_noise=self.gyro_noise, acc_noise=self.acc_noise,
            integration_noise=self.integration_noise, prefix=prefix, scheme=self.scheme,
            check=check,
        )

    def predict(self, state: NavState, pre: Preintegrated, gyro_bias: Any = None,
                acc_bias: Any = None) -> NavState:
        """State at the window end from ``state`` at its start, with this module's gravity
        (see :func:`predict`)."""
        return predict(state, pre, self.gravity, gyro_bias, acc_bias)

    def dead_reckon(self, gyro: Any, acc: Any, dt: Any, init: NavState | None = None,
                    gyro_bias: Any = None, acc_bias: Any = None) -> NavState:
        """Dead-reckoned states after every sample (see :func:`dead_reckon`)."""
        return dead_reckon(gyro, acc, dt, self.gravity, init, gyro_bias=gyro_bias,
                           acc_bias=acc_bias, scheme=self.scheme)
