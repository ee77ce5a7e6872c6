"""Damping strategies: PyPose's update rules, clamps, and the dogleg step."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jaxpose.optim as jo
from jaxpose.optim import Cholesky, NormalEquations

F64 = jnp.float64


def _upd(strategy, state, ratio, step_norm=1.0):
    return strategy.update(state, jnp.asarray(ratio, F64), jnp.asarray(step_norm, F64))


def test_constant_never_changes():
    st = jo.Constant(1e-3)
    s = st.init(F64)
    for r in (-np.inf, -1.0, 0.0, 0.4, 0.9):
        s = _upd(st, s, r)
        assert float(st.damping(s)) == 1e-3


def test_adaptive_rule_and_clamps():
    st = jo.Adaptive(damping=1.0, high=0.5, low=1e-3, up=3.0, down=0.25, min=1e-2, max=10.0)
    s = st.init(F64)
    s = _upd(st, s, 0.9)  # very successful: λ·down
    assert float(s) == pytest.approx(0.25)
    s = _upd(st, s, 0.1)  # successful: unchanged
    assert float(s) == pytest.approx(0.25)
    s = _upd(st, s, 1e-4)  # unsuccessful: λ·up
    assert float(s) == pytest.approx(0.75)
    s = _upd(st, s, -np.inf)  # failed / non-finite trial
    assert float(s) == pytest.approx(2.25)
    for _ in range(5):
        s = _upd(st, s, -1.0)
    assert float(s) == pytest.approx(10.0)  # clamped at max
    for _ in range(10):
        s = _upd(st, s, 1.0)
    assert float(s) == pytest.approx(1e-2)  # clamped at min


def test_trust_region_rule_and_down_factor():
    st = jo.TrustRegion(radius=8.0, high=0.5, low=1e-3, up=2.0, down=0.5, factor=0.5,
                        min=1e-3, max=100.0)
    s = st.init(F64)
    assert float(st.damping(s)) == pytest.approx(1 / 8)
    s = _upd(st, s, 0.9)  # radius·up
    assert 1 / float(s.damping) == pytest.approx(16.0) and float(s.down) == 0.5
    s = _upd(st, s, 0.2)  # unchanged radius, down reset
    assert 1 / float(s.damping) == pytest.approx(16.0)
    s = _upd(st, s, 0.0)  # radius·down, down·factor
    assert 1 / float(s.damping) == pytest.approx(8.0) and float(s.down) == pytest.approx(0.25)
    s = _upd(st, s, -1.0)  # shrinks faster after repeated failures
    assert 1 / float(s.damping) == pytest.approx(2.0) and float(s.down) == pytest.approx(0.125)
    s = _upd(st, s, 0.3)  # a successful step resets down
    assert float(s.down) == pytest.approx(0.5)
    for _ in range(20):
        s = _upd(st, s, 0.99)
    assert 1 / float(s.damping) == pytest.approx(100.0)  # radius clamped at max
    for _ in range(30):
        s = _upd(st, s, -1.0)
    assert 1 / float(s.damping) == pytest.approx(1e-3)  # and at min
    assert float(s.down) == pytest.approx(1e-3)  # down clamped too (PyPose)


@pytest.mark.peer
@pytest.mark.parametrize("kind", ["Adaptive", "TrustRegion"])
def test_matches_pypose_update_sequence(kind):
    torch = pytest.importorskip("torch")
    pps = pytest.importorskip("pypose.optim.strategy")
    rng = np.random.default_rng(0)
    qualities = rng.choice([-np.inf, -0.5, 1e-4, 0.2, 0.7, 0.95], size=40)
    if kind == "Adaptive":
        theirs, ours = pps.Adaptive(damping=1e-3), jo.Adaptive(damping=1e-3)
    else:
        theirs, ours = pps.TrustRegion(radius=10.0), jo.TrustRegion(radius=10.0)
    pg = dict(theirs.defaults)
    s = ours.init(F64)
    # J = D = 1, R = -1 makes PyPose's predicted decrease exactly 1, so quality = last - loss
    one = torch.ones(1, 1, dtype=torch.float64)
    for q in qualities:
        last = torch.tensor(float(q) if np.isfinite(q) else -1e300, dtype=torch.float64)
        theirs.update(pg, last=last, loss=torch.tensor(0.0, dtype=torch.float64), J=one,
                      D=one, R=-one)
        s = _upd(ours, s, q)
        assert float(ours.damping(s)) == pytest.approx(float(pg["damping"]), rel=1e-12)


def _system(h, g):
    h = jnp.asarray(h, F64)
    g = jnp.asarray(g, F64)
    n = g.shape[0]
    jac = jnp.linalg.cholesky(h).T  # any J with JᵀJ = H
    return NormalEquations(jac, jnp.linalg.solve(jac.T, g), h, g, jnp.diagonal(h), jnp.zeros(n))


def test_lm_step_uses_fresh_damping():
    h = np.array([[4.0, 1.0], [1.0, 3.0]])
    g = np.array([1.0, -2.0])
    st = jo.Adaptive(damping=0.5)
    s = st.init(F64)
    d = st.step(s, _system(h, g), Cholesky())
    want = np.linalg.solve(h + 0.5 * np.diag(np.diag(h)), -g)
    np.testing.assert_allclose(d, want, rtol=1e-12)


def test_dogleg_three_regimes():
    h = np.array([[2.0, 0.3], [0.3, 1.0]])
    g = np.array([1.0, 1.0])
    gn = np.linalg.solve(h, -g)
    sd = -(g @ g) / (g @ h @ g) * g
    st = jo.Dogleg()
    sys_ = _system(h, g)
    # 1) GN step inside the region
    d = st.step(jnp.asarray(2 * np.linalg.norm(gn)), sys_, Cholesky())
    np.testing.assert_allclose(d, gn, rtol=1e-12)
    # 2) Cauchy point outside: clipped steepest descent
    r = 0.5 * np.linalg.norm(sd)
    d = st.step(jnp.asarray(r), sys_, Cholesky())
    np.testing.assert_allclose(d, -r * g / np.linalg.norm(g), rtol=1e-12)
    # 3) in between: on the boundary, on the segment sd -> gn
    r = 0.5 * (np.linalg.norm(sd) + np.linalg.norm(gn))
    d = np.asarray(st.step(jnp.asarray(r), sys_, Cholesky()))
    assert np.linalg.norm(d) == pytest.approx(r, rel=1e-12)
    seg = gn - sd
    tau = (d - sd) @ seg / (seg @ seg)
    assert 0 < tau < 1
    np.testing.assert_allclose(d, sd + tau * seg, rtol=1e-10, atol=1e-14)


def test_dogleg_radius_update():
    st = jo.Dogleg(radius=1.0, high=0.75, low=0.25, up=2.0, down=0.25, min=1e-3, max=3.0)
    s = st.init(F64)
    assert float(_upd(st, s, 0.1, 1.0)) == pytest.approx(0.25)  # poor: shrink
    assert float(_upd(st, s, 0.5, 1.0)) == pytest.approx(1.0)  # fine: keep
    assert float(_upd(st, s, 0.9, 0.5)) == pytest.approx(1.0)  # good but interior: keep
    assert float(_upd(st, s, 0.9, 1.0)) == pytest.approx(2.0)  # good on boundary: grow
    assert float(_upd(st, jnp.asarray(2.5, F64), 0.9, 2.5)) == pytest.approx(3.0)  # max
    assert float(st.damping(s)) == pytest.approx(1.0)


def test_invalid_strategy_parameters():
    with pytest.raises(ValueError, match="up"):
        jo.Adaptive(up=0.5)
    with pytest.raises(ValueError, match="down"):
        jo.TrustRegion(down=1.5)
    with pytest.raises(ValueError, match="damping"):
        jo.Constant(0.0)
    with pytest.raises(ValueError, match="radius"):
        jo.Dogleg(radius=-1.0)
