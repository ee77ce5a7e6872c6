"""GTSAM's fixed-lag smoothers fed the very factors of a jaxpose smoother stream.

The factors are ``gtsam.CustomFactor``s that evaluate the jaxpose residual functions and
their Jacobians (jitted), with the tangent columns mapped to GTSAM's charts: state
``{"bias", "pose": SE3, "vel"}`` → keys B(k) (Vector6), X(k) (Pose3, tangent ``[ω, v]``
where jaxpose's is ``[ρ, φ]``; both retract with ``X·Exp``), V(k) (Vector3). Unit noise
models: the residuals are already whitened.
"""

from __future__ import annotations

import gtsam
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from jaxpose.lie import SE3, manifold
from jaxpose.smoothing._fixed_lag import _take

X = lambda k: gtsam.symbol("x", k)  # noqa: E731
V = lambda k: gtsam.symbol("v", k)  # noqa: E731
B = lambda k: gtsam.symbol("b", k)  # noqa: E731
POSE_COLS = np.r_[3:6, 0:3]  # gtsam [ω, v] ← jaxpose [ρ, φ]


def _keys(k):
    return [B(k), X(k), V(k)]


def _split(jac):
    """(r, 15) jaxpose state Jacobian → GTSAM blocks [B, X, V]."""
    return [jac[:, 0:6], jac[:, 6:12][:, POSE_COLS], jac[:, 12:15]]


def _state(values, k):
    pose = SE3.from_matrix(jnp.asarray(values.atPose3(X(k)).matrix()))
    return {
        "bias": jnp.asarray(values.atVector(B(k))),
        "pose": pose,
        "vel": jnp.asarray(values.atVector(V(k))),
    }


def _plus(x, e):
    unravel = ravel_pytree(manifold.zero_tangent(x))[1]
    return manifold.retract(x, unravel(e))


def make_factors(motion, unary):
    """Jitted (residual, Jacobian) of the motion and unary functions of a stream."""

    @jax.jit
    def motion_rj(xp, x, d):
        f = lambda e: motion(_plus(xp, e[:15]), _plus(x, e[15:]), d)  # noqa: E731
        z = jnp.zeros(30)
        return f(z), jax.jacfwd(f)(z)

    @jax.jit
    def unary_rj(x, d):
        f = lambda e: unary(_plus(x, e), d)  # noqa: E731
        z = jnp.zeros(15)
        return f(z), jax.jacfwd(f)(z)

    def motion_factor(k, d):
        def err(this, values, H):
            r, j = motion_rj(_state(values, k - 1), _state(values, k), d)
            if H is not None:
                j = np.asarray(j)
                for i, blk in enumerate(_split(j[:, :15]) + _split(j[:, 15:])):
                    H[i] = np.ascontiguousarray(blk)
            return np.asarray(r)

        dim = int(motion_rj(_state_zero(), _state_zero(), d)[0].shape[0])
        return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(dim), _keys(k - 1) + _keys(k), err)

    def unary_factor(k, d):
        def err(this, values, H):
            r, j = unary_rj(_state(values, k), d)
            if H is not None:
                for i, blk in enumerate(_split(np.asarray(j))):
                    H[i] = np.ascontiguousarray(blk)
            return np.asarray(r)

        dim = int(unary_rj(_state_zero(), d)[0].shape[0])
        return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(dim), _keys(k), err)

    return motion_factor, unary_factor


def _state_zero():
    return {"bias": jnp.zeros(6), "pose": SE3.identity(dtype=jnp.float64), "vel": jnp.zeros(3)}


def _values(k, x):
    v = gtsam.Values()
    v.insert(B(k), np.asarray(x["bias"], np.float64))
    v.insert(X(k), gtsam.Pose3(np.asarray(x["pose"].matrix(), np.float64)))
    v.insert(V(k), np.asarray(x["vel"], np.float64))
    return v


def run_batch(steps, guesses, window, motion, unary):
    """Replay ``steps`` (with the given initial values per step) through GTSAM's
    ``BatchFixedLagSmoother`` (lag window − 2 with unit timestamps: it optimises the same
    ``window`` states as jaxpose per update). Returns per step the newest estimate
    (dict of numpy arrays)."""
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(0.0)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(100)
    smoother = gtsam.BatchFixedLagSmoother(float(window - 2), params)
    motion_factor, unary_factor = make_factors(motion, unary)
    t = jax.tree.leaves(steps.data)[0].shape[0]
    out = []
    for k in range(t):
        d = _take(steps.data, k)
        graph = gtsam.NonlinearFactorGraph()
        if k > 0:
            graph.add(motion_factor(k, d))
        graph.add(unary_factor(k, d))
        stamps = {B(k): float(k), X(k): float(k), V(k): float(k)}
        smoother.update(graph, _values(k, _take(guesses, k)), stamps)
        est = smoother.calculateEstimate()
        out.append(_state(est, k))
    return jax.tree.map(lambda *a: np.stack(a), *out)
