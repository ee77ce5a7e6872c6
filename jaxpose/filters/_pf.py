"""Bootstrap particle filter with systematic resampling.

Same model convention as :class:`~jaxpose.filters.EKF`. Each step propagates every
particle through ``f`` plus tangent-space process noise ``w ~ N(0, Q)`` (``x ⊕ w`` for
group states), reweights by the Gaussian likelihood ``N(y ⊖ h(x); 0, R)``, reports the
weighted mean and covariance and the effective sample size ``ESS = 1 / Σ w_i²``, and
resamples systematically when ``ESS < threshold · N``. Weights are kept as
log-weights. Randomness comes from an explicit PRNG key.

The likelihoods are scale-safe (squares formed after scaling by the largest innovation):
a finite but absurd measurement (1e200) gives all weight to the particles nearest to it
instead of NaN weights. Singular ``Q``/``P0`` (positive semi-definite) spread the
particles only along their range. ``skip_nonfinite`` as in :mod:`~jaxpose.filters._ekf`:
a measurement that is not finite, or whose normalised innovation overflows for every
particle, leaves the weights unchanged (propagation only).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import check_count
from .._dtypes import keep_dtypes
from .._precision import full_precision
from ..dynamics._system import System
from ..dynamics._tangent import tangent_space
from ._common import (
    FilterResult,
    check_cov,
    check_measurement,
    check_noise_dim,
    check_sequence,
    finite_tree,
    psd_cholesky,
    relative_loglik,
    select_tree,
)
from ._kalman import NoisyModelFilter

Array = jax.Array


class ParticleState(eqx.Module):
    """``particles`` (N, …) and normalised ``log_weights`` (N,)."""

    particles: Any
    log_weights: Array


def effective_sample_size(log_weights: Array) -> Array:
    """``1 / Σ w_i²`` for normalised log-weights."""
    w = jnp.exp(log_weights - jax.scipy.special.logsumexp(log_weights))
    return 1.0 / jnp.sum(w * w)


def systematic_resample(key: Array, log_weights: Array) -> Array:
    """Indices (N,) by systematic resampling: one uniform offset, N evenly spaced
    positions on the cumulative weights (low variance, O(N log N))."""
    N = log_weights.shape[0]
    w = jnp.exp(log_weights - jax.scipy.special.logsumexp(log_weights))
    cdf = jnp.cumsum(w)
    cdf = cdf / cdf[-1]
    pos = (jax.random.uniform(key, (), w.dtype) + jnp.arange(N, dtype=w.dtype)) / N
    return jnp.clip(jnp.searchsorted(cdf, pos, side="right"), 0, N - 1)


class ParticleFilter(NoisyModelFilter):
    """``ParticleFilter(model, Q, R, num_particles=1000, resample_threshold=0.5,
    skip_nonfinite=False)``."""

    num_particles: int = eqx.field(static=True, default=1000)
    resample_threshold: float = eqx.field(static=True, default=0.5)

    def __init__(
        self,
        model: System,
        Q: Any,
        R: Any,
        num_particles: int = 1000,
        resample_threshold: float = 0.5,
        skip_nonfinite: bool = False,
    ):
        super().__init__(model, Q, R, skip_nonfinite)
        num_particles = check_count(num_particles, "num_particles")
        if not 0.0 <= resample_threshold <= 1.0:
            raise ValueError(
                f"resample_threshold: expected a fraction in [0, 1], got {resample_threshold}"
            )
        self.num_particles = num_particles
        self.resample_threshold = float(resample_threshold)

    @full_precision
    def init(self, key: Array, x0: Any, P0: Any) -> ParticleState:
        """Particles drawn from ``x0 ⊕ N(0, P0)`` with equal weights."""
        ts = tangent_space(x0)
        P0 = check_cov(P0, ts.dim, "P0", once=True)
        N = self.num_particles
        L = psd_cholesky(P0)  # P0 = 0 → all particles at x0
        dtype = jax.tree.leaves(x0)[0].dtype  # the particles keep x0's dtype
        d = jax.random.normal(key, (N, ts.dim), dtype) @ L.T.astype(dtype)
        parts = jax.vmap(lambda e: ts.plus(x0, e))(d)
        return ParticleState(parts, jnp.full((N,), -jnp.log(N), dtype))

    @full_precision
    def estimate(self, state: ParticleState) -> tuple[Any, Array]:
        """Weighted mean and covariance (tangent coordinates) of the particles."""
        w = jnp.exp(state.log_weights - jax.scipy.special.logsumexp(state.log_weights))
        first = jax.tree.map(lambda a: a[0], state.particles)
        ts = tangent_space(first)
        if ts.euclidean:
            mean = w @ state.particles
            dev = state.particles - mean
        else:
            best = jax.tree.map(lambda a: a[jnp.argmax(w)], state.particles)
            local = jax.vmap(lambda p: ts.minus(p, best))(state.particles)
            mean = ts.plus(best, w @ local)
            dev = jax.vmap(lambda p: ts.minus(p, mean))(state.particles)
        cov = (w[:, None] * dev).T @ dev
        return mean, 0.5 * (cov + cov.T)

    def step(
        self, key: Array, state: ParticleState, y: Any, u: Array, t: Any = 0
    ) -> tuple[ParticleState, tuple[Any, Array, Array]]:
        """Propagate, reweight, estimate, resample if needed. Returns the new state and
        ``(mean, cov, ess)`` (estimates before resampling). Compiled on first call
        (``eqx.filter_jit``; ``t`` is passed as an array)."""
        return _compiled_step(self._noise_checked(once=False), key, state, y, u,
                              jnp.asarray(t))

    def _factors(self) -> tuple[Array, Array]:
        """Cholesky factor of Q (positive semi-definite: zero columns where Q is singular,
        no noise there) and the inverse Cholesky factor of R, computed once per run rather
        than per step."""
        Lq = psd_cholesky(self.Q)
        Lr = jnp.linalg.cholesky(self.R)
        eye = jnp.eye(self.R.shape[0], dtype=Lr.dtype)
        return Lq, jax.scipy.linalg.solve_triangular(Lr, eye, lower=True)

    def _step(
        self,
        key: Array,
        state: ParticleState,
        y: Any,
        u: Array,
        t: Any,
        Lq: Array,
        Lr_inv: Array,
    ) -> tuple[ParticleState, tuple[Any, Array, Array], Array]:
        k_noise, k_res = jax.random.split(key)
        N = self.num_particles
        first = jax.tree.map(lambda a: a[0], state.particles)
        ts = tangent_space(first)
        check_noise_dim(self.Q, ts.dim, "Q", "state tangent size")
        noise = jax.random.normal(k_noise, (N, ts.dim), self.Q.dtype) @ Lq.T
        parts = jax.vmap(lambda p, e: ts.plus(self.model.state_transition(p, u, t), e))(
            state.particles, noise
        )
        obs = jax.vmap(lambda p: self.model.observation(p, u, t))(parts)
        yts = tangent_space(jax.tree.map(lambda a: a[0], obs))
        check_noise_dim(self.R, yts.dim, "R", f"measurement noise: h(x) gives {yts.dim} values")
        first_obs = jax.tree.map(lambda a: a[0], obs)
        check_measurement(y, first_obs, self.R)
        use = jnp.asarray(True)
        if self.skip_nonfinite:
            use = finite_tree(y)
            y = select_tree(use, y, first_obs)
        r = jax.vmap(lambda o: yts.minus(y, o))(obs)
        ll, nis_min = relative_loglik(r, Lr_inv)
        if self.skip_nonfinite:
            use = use & jnp.isfinite(nis_min)
            ll = jnp.where(use, ll, 0.0)
        logw = state.log_weights + ll
        logw = jnp.where(jnp.isfinite(logw), logw, -jnp.inf)
        logw = logw - jax.scipy.special.logsumexp(logw)
        new = ParticleState(parts, logw)
        mean, cov = self.estimate(new)
        ess = effective_sample_size(logw)
        idx = systematic_resample(k_res, logw)
        do = ess < self.resample_threshold * N
        resampled = ParticleState(
            jax.tree.map(lambda a: a[idx], parts), jnp.full((N,), -jnp.log(N), logw.dtype)
        )
        new = jax.tree.map(lambda a, b: jnp.where(do, a, b), resampled, new)
        return new, (mean, cov, ess), use

    def run(
        self, key: Array, x0: Any, P0: Any, ys: Any, us: Array, t0: Any = 0
    ) -> tuple[FilterResult, Array]:
        """Filter a sequence with ``lax.scan``; returns the per-step estimates
        (:class:`FilterResult`) and the ESS (N,) before resampling. Sizes are checked at
        trace time as in :meth:`EKF.run <jaxpose.filters.EKF.run>`. Compiled on first
        call (``eqx.filter_jit``)."""
        P0 = check_cov(P0, tangent_space(x0).dim, "P0", once=True)
        return _compiled_run(self._noise_checked(once=True), key, x0, P0, ys, us,
                             jnp.asarray(t0))

    def _run(self, key: Array, x0: Any, P0: Any, ys: Any, us: Array,
             t0: Array) -> tuple[FilterResult, Array]:
        us = check_sequence(self.model, self.R, x0, ys, us, t0)
        n_y = jax.tree.leaves(ys)[0].shape[0]
        k0, key = jax.random.split(key)
        state = self.init(k0, x0, P0)
        keys = jax.random.split(key, n_y)
        ts = jnp.asarray(t0) + jnp.arange(n_y)
        factors = self._factors()

        def body(s: ParticleState, inp: tuple[Array, Any, Array, Array]):
            k, y, u, t = inp
            new, (mean, cov, ess), used = self._step(k, s, y, u, t, *factors)
            s = keep_dtypes(new, s)  # float64 model/noise data: particles keep x0's dtype
            mean = keep_dtypes(mean, s.particles)
            cov = cov.astype(s.log_weights.dtype)  # (x0's dtype)
            return s, (mean, cov, ess, used & finite_tree(mean, cov))

        _, (means, covs, ess, ok) = jax.lax.scan(body, state, (keys, ys, us, ts))
        return FilterResult(means, covs, ok), ess


@eqx.filter_jit
@full_precision
def _compiled_step(filt: ParticleFilter, key: Array, state: ParticleState, y: Any, u: Array,
                   t: Array) -> tuple[ParticleState, tuple[Any, Array, Array]]:
    return filt._step(key, state, y, u, t, *filt._factors())[:2]


@eqx.filter_jit
@full_precision
def _compiled_run(filt: ParticleFilter, key: Array, x0: Any, P0: Any, ys: Any, us: Array,
                  t0: Array) -> tuple[FilterResult, Array]:
    return filt._run(key, x0, P0, ys, us, t0)
