"""Small test problems with independent numpy references (no jaxpose code involved)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

_rng = np.random.default_rng(42)
T_EXP = np.linspace(0.0, 2.0, 20)
Y_EXP = 2.0 * np.exp(-1.3 * T_EXP) + 0.02 * _rng.normal(size=20)


def exp_residual(p, args):
    """Exponential decay fit: blocks (20, 1) of a·exp(−b t) − y."""
    t, y = args
    return (p[0] * jnp.exp(-p[1] * t) - y)[:, None]


def exp_jacobian(p, args):
    """Analytic (20, 2) Jacobian of :func:`exp_residual`."""
    t, _ = args
    e = jnp.exp(-p[1] * t)
    return jnp.stack([e, -p[0] * t * e], 1)


def exp_reference(t=T_EXP, y=Y_EXP):
    """Optimum of 0.5‖a·exp(−b t) − y‖² by a numpy Gauss-Newton loop."""
    p = np.array([1.5, 1.0])
    for _ in range(200):
        e = np.exp(-p[1] * t)
        r = p[0] * e - y
        j = np.stack([e, -p[0] * t * e], 1)
        p = p + np.linalg.lstsq(j, -r, rcond=None)[0]
    return p


EXP_ARGS = (jnp.asarray(T_EXP), jnp.asarray(Y_EXP))
EXP_OPT = exp_reference()
