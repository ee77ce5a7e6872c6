"""vmap over 1000 independent problems: each converges to its own known answer."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxpose as jp
import jaxpose.optim as jo
from jaxpose.lie import SE3

B = 1000


def circle_residual(p, pts):
    """Distance of each point to the circle (c, r): blocks (n, 1)."""
    d = pts - p["c"]
    return (jnp.sqrt(jnp.sum(d * d, -1)) - p["r"])[:, None]


def _circles(seed, n=12):
    rng = np.random.default_rng(seed)
    c = rng.uniform(-5, 5, size=(B, 2))
    r = rng.uniform(0.5, 3.0, size=B)
    start = rng.uniform(0, 2 * np.pi, size=(B, 1))
    span = rng.uniform(0.5 * np.pi, 2 * np.pi, size=(B, 1))  # arcs of 90° to 360°
    ang = start + span * np.linspace(0, 1, n, endpoint=False)
    pts = c[:, None] + r[:, None, None] * np.stack([np.cos(ang), np.sin(ang)], -1)
    return c, r, pts


def test_vmap_1000_circle_fits_each_converge():
    c, r, pts = _circles(0)
    pts = jnp.asarray(pts)
    # deliberately rough start: centroid and mean distance to it
    c0 = jnp.mean(pts, 1)
    init = {"c": c0, "r": jnp.mean(jnp.linalg.norm(pts - c0[:, None], axis=-1), -1)}
    solve = jax.jit(jax.vmap(lambda p, x: jo.least_squares(circle_residual, p, x)))
    sol = solve(init, pts)
    assert np.all(np.asarray(sol.status) == jp.Results.CONVERGED)
    np.testing.assert_allclose(sol.params["c"], c, atol=1e-8)
    np.testing.assert_allclose(sol.params["r"], r, atol=1e-8)
    # every problem stops on its own: iteration counts differ across the batch, and a
    # problem solved alone takes exactly the same path as inside the batch
    steps = np.asarray(sol.num_steps)
    assert steps.min() < steps.max()
    single = jax.jit(lambda p, x: jo.least_squares(circle_residual, p, x))
    for i in (int(np.argmin(steps)), int(np.argmax(steps)), 7):
        one = single(jax.tree.map(lambda a: a[i], init), pts[i])
        assert int(one.num_steps) == steps[i]
        np.testing.assert_allclose(one.params["c"], sol.params["c"][i], rtol=1e-12)


def pose_residual(x, meas):
    """Log(Tᵢ⁻¹ X) for each measurement Tᵢ: blocks (k, 6)."""
    return (meas.inv() @ x).log().data


def test_vmap_1000_se3_pose_averages_with_outliers_under_huber():
    k_in, k_out = 8, 2
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    f32 = jnp.float32
    truth = SE3.random(keys[0], (B,), sigma=1.0, dtype=f32)
    noise = jnp.concatenate([
        0.01 * jax.random.normal(keys[1], (B, k_in, 6), f32),
        1.5 * jax.random.normal(keys[2], (B, k_out, 6), f32),  # gross outliers
    ], 1)
    meas = SE3(truth.data[:, None]) @ SE3.exp(noise)
    init = meas[:, 0]  # an inlier
    solve = jax.jit(jax.vmap(lambda x, m: jo.least_squares(
        pose_residual, x, m, kernel=jo.Huber(0.05), max_steps=50)))
    sol = solve(init, meas)
    assert sol.params.dtype == f32
    assert np.all(np.asarray(sol.status) == jp.Results.CONVERGED)
    err = np.linalg.norm(np.asarray((truth.inv() @ sol.params).log().data), axis=-1)
    # Huber caps each outlier's pull at δ: error ≲ noise + 2δ/8; a plain average would be
    # dragged ~0.3 away by the outliers
    assert err.max() < 0.05, err.max()
    assert np.median(err) < 0.02
    assert np.all(np.asarray(sol.cost) < np.asarray(sol.initial_cost))
