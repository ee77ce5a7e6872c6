"""Splines: interpolation through control points, continuity of derivatives at the
knots, closed-form special cases, PyPose parity."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.geometry import bspline, bspline_se3, bspline_se3_fit, chspline, hermite
from jaxpose.lie import SE3

from .conftest import pypose


def _trajectory(rng, n=7, step=0.3):
    return SE3.exp(jnp.asarray(np.cumsum(rng.normal(size=(n, 6)) * step, 0)))


def test_bspline_closed_form_cases():
    # identical controls → constant
    c = SE3.exp(jnp.array([0.3, -0.2, 0.1, 0.4, 0.2, -0.1]))
    same = SE3(jnp.broadcast_to(c.data, (5, 7)))
    out = bspline_se3(same, jnp.linspace(0, 2, 9))
    np.testing.assert_allclose(out.matrix(), np.broadcast_to(c.matrix(), (9, 4, 4)), atol=1e-14)
    # uniformly spaced pure translations: the curve is linear, T(t) = controls at t + 1
    lin = SE3(jnp.concatenate([jnp.arange(6.0)[:, None] * jnp.array([1.0, 2.0, -1.0]),
                               jnp.broadcast_to(jnp.array([0.0, 0, 0, 1]), (6, 4))], -1))
    t = jnp.array([0.0, 0.25, 1.5, 2.999, 3.0])
    np.testing.assert_allclose(bspline_se3(lin, t).translation(),
                               (t + 1.0)[:, None] * np.array([1.0, 2.0, -1.0]), atol=1e-13)


def test_fit_passes_through_poses_and_is_c2(rng):
    poses = _trajectory(rng)
    ctrl = jax.jit(bspline_se3_fit)(poses)
    assert ctrl.shape == (9,)
    at_knots = bspline_se3(ctrl, jnp.arange(7.0))
    np.testing.assert_allclose(at_knots.matrix(), poses.matrix(), atol=1e-12)

    def curve(t):  # translation and rotation vector (smooth charts)
        x = bspline_se3(ctrl, t[None])[0]
        return jnp.concatenate([x.translation(), (poses[3].inv() @ x).rotation().log().data])

    d1 = jax.jit(jax.vmap(jax.jacfwd(curve)))
    for knot in (2.0, 3.0, 4.0):
        # first derivative: autodiff just left / right of the knot (and at it)
        h = 1e-4
        t = jnp.asarray([knot - 1e-9, knot + 1e-9, knot - 2 * h, knot - h, knot + h,
                         knot + 2 * h])
        v = np.asarray(d1(t))
        np.testing.assert_allclose(v[0], v[1], atol=1e-7)
        # second derivative: one-sided differences of the first on each side agree
        left, right = (v[3] - v[2]) / h, (v[5] - v[4]) / h
        np.testing.assert_allclose(left, right, atol=1e-2 * (1 + np.abs(left).max()))


def test_hermite_interpolates_and_reproduces_cubics(rng):
    times = np.cumsum(rng.uniform(0.2, 1.0, 6))
    pts = rng.normal(size=(6, 3))
    f = jax.jit(hermite)
    np.testing.assert_allclose(f(pts, times, times), pts, atol=1e-14)
    # exact tangents of a cubic polynomial → the cubic itself everywhere
    coef = rng.normal(size=(4, 2))
    poly = lambda t: np.stack([coef[0, i] + coef[1, i] * t + coef[2, i] * t ** 2
                               + coef[3, i] * t ** 3 for i in range(2)], -1)
    dpoly = lambda t: np.stack([coef[1, i] + 2 * coef[2, i] * t + 3 * coef[3, i] * t ** 2
                                for i in range(2)], -1)
    tq = np.linspace(times[0], times[-1], 23)
    got = hermite(poly(times), tq, times, tangents=dpoly(times))
    np.testing.assert_allclose(got, poly(tq), atol=1e-12)
    # C¹ at interior knots (default tangents)
    dt = jax.jit(jax.jacfwd(lambda t: hermite(pts, t[None], times)[0]))
    for knot in times[1:-1]:
        np.testing.assert_allclose(dt(jnp.asarray(knot - 1e-9)), dt(jnp.asarray(knot + 1e-9)),
                                   atol=1e-6)


def test_jit_vmap_grad(rng):
    poses = _trajectory(rng, 6)
    batch = SE3(jnp.stack([poses.data, poses.data[::-1]]))
    t = jnp.array([0.3, 1.7, 2.5])
    vm = jax.jit(jax.vmap(lambda c: bspline_se3(SE3(c), t).data))(batch.data)
    np.testing.assert_allclose(vm, bspline_se3(batch, t).data, atol=1e-14)
    g = jax.jit(jax.grad(lambda c, tt: jnp.sum(bspline_se3(SE3(c), tt).translation()),
                         argnums=(0, 1)))(poses.data, t)
    assert all(np.all(np.isfinite(x)) for x in g)
    gh = jax.grad(lambda p: jnp.sum(hermite(p, t) ** 2))(jnp.asarray(rng.normal(size=(5, 2))))
    assert np.all(np.isfinite(gh))


@pytest.mark.peer
def test_pypose_parity(rng):
    pp = pypose()
    import torch

    poses = _trajectory(rng, 7)
    for extrapolate in (False, True):
        ours = bspline(poses, 0.25, extrapolate=extrapolate)
        ref = pp.bspline(pp.SE3(torch.tensor(np.asarray(poses.data))), 0.25,
                         extrapolate=extrapolate)
        np.testing.assert_allclose(ours.data, ref.numpy(), atol=1e-12)
    pts = rng.normal(size=(2, 6, 3))
    np.testing.assert_allclose(chspline(pts, 0.2), pp.chspline(torch.tensor(pts), 0.2).numpy(),
                               atol=1e-12)


def test_bad_input(rng):
    with pytest.raises(ValueError, match=r"bspline_se3\(control\).*at least 4"):
        bspline_se3(SE3.identity((3,)), jnp.zeros(2))
    with pytest.raises(TypeError, match=r"bspline_se3\(control\).*SE3"):
        bspline_se3(np.zeros((5, 7)), jnp.zeros(2))
    with pytest.raises(ValueError, match=r"bspline_se3_fit\(poses\).*at least 2"):
        bspline_se3_fit(SE3.identity((1,)))
    with pytest.raises(ValueError, match=r"hermite\(times\)"):
        hermite(np.zeros((5, 2)), 0.5, times=np.arange(4.0))
    with pytest.raises(ValueError, match=r"hermite\(points\).*at least 2"):
        hermite(np.zeros((1, 2)), 0.5)
    with pytest.raises(ValueError, match=r"chspline\(interval\)"):
        chspline(np.zeros((5, 2)), 1.5)


def test_hermite_with_epoch_second_knot_times_in_float32():
    """Knot times in epoch seconds (1.6e9; float32 spacing 128 s) with float32 points (the
    spline's dtype): t rounded to the 128 s grid gave [0.5, 1.5] for [0.5003, 1.4999]
    (and the same with x64 off). Host times are shifted to a common origin first."""
    pts = np.array([[0.0], [1.0], [2.0]], np.float32)  # linear in t: p = (t − t0) / 1000
    t0 = 1.6e9
    times, t = t0 + np.array([0.0, 1000.0, 2000.0]), t0 + np.array([500.3, 1499.9])
    want = (t - t0)[:, None] / 1000.0
    np.testing.assert_allclose(hermite(pts, t, times=times), want, rtol=1e-6)
    with jax.enable_x64(False):
        np.testing.assert_allclose(hermite(pts, t, times=times), want, rtol=1e-6)
