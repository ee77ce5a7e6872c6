"""FixedLagSmoother: closed forms on a linear-Gaussian chain, marginalisation against the
full batch solve, vmap over streams, bad input, and the 2D pose-graph replay.

Reference for the linear case (independent of the code under test): with linear factors
and a window that never drops information, the smoother's newest estimate and its
covariance equal the Kalman filter's (the marginal of the full batch posterior), and
every window estimate equals the fixed-lag smoothed batch solution restricted to the
factors seen so far.
"""

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.graph._factor import between_residual
from jaxpose.lie import SE2
from jaxpose.smoothing import FixedLagSmoother
from jaxpose.smoothing import examples as ex

Q, R = 0.3, 0.5  # random-walk and measurement σ


def _motion(xp, x, d):
    return (x["p"] - xp["p"]) / Q


def _unary(x, d):
    return jnp.concatenate([(x["p"] - d["z"]) / R, d["w"] * x["p"] / 10.0])


def _linear_stream(t, seed=0):
    rng = np.random.default_rng(seed)
    z = np.cumsum(rng.normal(size=(t, 2)) * Q, 0) + rng.normal(size=(t, 2)) * R
    w = np.zeros(t)
    w[0] = 1.0
    return {"z": jnp.asarray(z), "w": jnp.asarray(w)}


def _batch(data, t):
    """Dense least squares over all t states (numpy): the information matrix and mean."""
    n = 2 * t
    a, b = [], []
    for k in range(t):
        row = np.zeros((2, n))
        row[:, 2 * k : 2 * k + 2] = np.eye(2) / R
        a.append(row)
        b.append(np.asarray(data["z"][k]) / R)
        if k == 0:
            row = np.zeros((2, n))
            row[:, 0:2] = np.eye(2) / 10.0
            a.append(row)
            b.append(np.zeros(2))
        else:
            row = np.zeros((2, n))
            row[:, 2 * k - 2 : 2 * k] = -np.eye(2) / Q
            row[:, 2 * k : 2 * k + 2] = np.eye(2) / Q
            a.append(row)
            b.append(np.zeros(2))
    a, b = np.concatenate(a), np.concatenate(b)
    h = a.T @ a
    return h, np.linalg.solve(h, a.T @ b)


def _smoother(window, dense=False, **kw):
    """``dense``: one (never valid) loop slot forces the dense window system instead of
    the block-tridiagonal chain solver."""
    x0 = {"p": jnp.zeros(2)}
    d0 = {"z": jnp.zeros(2), "w": jnp.zeros(())}
    if dense:
        kw.update(loop=_motion, loop_data=d0, max_loops=1)
    return FixedLagSmoother(x0, d0, window=window, motion=_motion, unary=_unary, **kw)


@jax.jit
def _run_linear(sm, data):
    def body(s, d):
        if s.chain:
            s = s.update({"p": s.latest()["p"]}, d)
        else:
            ld = jax.tree.map(lambda a: a[None], d)
            s = s.update({"p": s.latest()["p"]}, d, jnp.ones(1, int), jnp.zeros(1, bool), ld)
        return s, (s.latest()["p"], s.marginal_covariances()[-1])

    return jax.lax.scan(body, sm, data)


MODES = {
    "chain": {},
    "dense": {"dense": True},
    # linear factors: one solve at any linearisation point is exact, so the incremental
    # mode must equal the batch solution whether or not it re-linearises
    "incremental": {"relinearize_threshold": float("inf")},
    "incremental-relinearizing": {"relinearize_threshold": 0.0},
}


@pytest.mark.parametrize("mode", MODES)
def test_linear_chain_equals_batch_marginals(mode):
    t, k = 9, 4
    data = _linear_stream(t)
    sm, (latest, cov) = _run_linear(_smoother(k, **MODES[mode]), data)
    assert sm.chain != (mode == "dense")
    if mode.startswith("incremental"):
        assert int(sm.iterations) == (mode == "incremental-relinearizing")
    for j in range(1, t + 1):
        h, mean = _batch(jax.tree.map(lambda a: a[:j], data), j)
        np.testing.assert_allclose(latest[j - 1], mean[-2:], atol=1e-9)
        np.testing.assert_allclose(cov[j - 1], np.linalg.inv(h)[-2:, -2:], atol=1e-9)
    # the whole final window: the batch solution and marginal covariances of its states
    h, mean = _batch(data, t)
    np.testing.assert_allclose(sm.states["p"], mean.reshape(t, 2)[-k:], atol=1e-9)
    full_cov = np.linalg.inv(h).reshape(t, 2, t, 2)
    blocks = np.stack([full_cov[i, :, i, :] for i in range(t - k, t)])
    np.testing.assert_allclose(sm.marginal_covariances(), blocks, atol=1e-9)
    assert sm.count == k and bool(sm.frozen[0]) and not bool(sm.frozen[1:].any())


@pytest.mark.parametrize("threshold", [None, 0.1])
def test_vmap_over_streams_equals_separate_runs(threshold):
    t, k = 7, 3
    datas = [_linear_stream(t, seed) for seed in (1, 2, 3)]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *datas)
    kw = {"relinearize_threshold": threshold}
    sms = eqx.filter_vmap(lambda _: _smoother(k, **kw), axis_size=3)(jnp.arange(3))
    out, (latest, _) = jax.vmap(_run_linear.__wrapped__)(sms, stacked)
    for i, data in enumerate(datas):
        _, (ref, _) = _run_linear(_smoother(k, **kw), data)
        np.testing.assert_allclose(latest[i], ref, atol=1e-12)


def test_bad_input():
    with pytest.raises(ValueError, match="window"):
        _smoother(1)
    with pytest.raises(TypeError, match="motion"):
        FixedLagSmoother({"p": jnp.zeros(2)}, {}, window=3, motion=None)
    sm = _smoother(3)
    with pytest.raises(TypeError, match="guess"):
        sm.update({"q": jnp.zeros(2)}, {"z": jnp.zeros(2), "w": jnp.zeros(())})
    with pytest.raises(ValueError, match="guess"):
        sm.update({"p": jnp.zeros(3)}, {"z": jnp.zeros(2), "w": jnp.zeros(())})
    with pytest.raises(Exception, match="non-finite"):
        jax.block_until_ready(sm.update({"p": jnp.array([jnp.nan, 0.0])},
                                        {"z": jnp.zeros(2), "w": jnp.zeros(())}))
    for kw in ({"dense": True}, {"first_estimate": False}):
        with pytest.raises(ValueError, match="relinearize_threshold.*max_loops=0"):
            _smoother(3, relinearize_threshold=0.1, **kw)
    with pytest.raises(ValueError, match="relinearize_threshold.*>= 0"):
        _smoother(3, relinearize_threshold=-1.0)
    with pytest.raises(ValueError, match=r"relinearize_skip\): expected an int >= 1"):
        _smoother(3, relinearize_threshold=0.1, relinearize_skip=0)
    with pytest.raises(ValueError, match="relinearize_skip.*relinearize_threshold"):
        _smoother(3, relinearize_skip=2)


DATA = os.path.join(os.path.dirname(__file__), "..", "..", "..", "shared", "data", "g2o")


def test_pose_graph_replay_window_covering_the_graph_equals_batch():
    """With a window as long as the stream nothing is marginalised: the final window is the
    batch solution of the same graph (pose 0 under the same prior)."""
    path = os.path.join(DATA, "intel.g2o")
    if not os.path.exists(path):
        pytest.skip("intel.g2o not available")
    from jaxpose.graph import _pgo as pgo
    from jaxpose.io import read_g2o

    n = 12
    graph = read_g2o(path)
    steps = ex.pose_graph_steps(graph, num_poses=n)
    res = ex.run(ex.pose_graph_smoother(steps, n), steps)
    keep = graph.edges.max(1) < n
    sub = type(graph)(
        kind="SE2",
        vertex_ids=graph.vertex_ids[:n],
        poses=graph.poses[:n],
        edges=graph.edges[keep],
        measurements=graph.measurements[keep],
        information=graph.information[keep],
    )
    ref_poses, _ = pgo.optimize_pose_graph(sub, fix="first")
    got = np.asarray(res.trajectory["pose"].data)
    np.testing.assert_allclose(got, ref_poses, atol=1e-5)
    assert isinstance(res.latest["pose"], SE2)
    assert res.status.shape == (n,) and np.all(np.asarray(res.status) == 0)  # converged


# ---------------------------------------------------------------- incremental updates
def _se2_motion(xp, x, d):
    return between_residual(xp["pose"], x["pose"], SE2(d["z"])) / 0.05


def _se2_unary(x, d):
    """A position fix (σ 0.5) and, on the first pose only (w = 1), a prior at identity."""
    fix = (x["pose"].translation() - d["gps"]) / 0.5
    return jnp.concatenate([fix, d["w"] * x["pose"].log().data / 0.01])


def _se2_stream(t, seed=0):
    """Noisy odometry and position fixes of a curving SE2 trajectory (float64)."""
    rng = np.random.default_rng(seed)
    u = np.stack([np.ones(t), np.zeros(t), 0.3 * np.sin(np.arange(t) / 3)], 1)
    true = SE2.exp(jnp.asarray(u)).data  # per-step motions
    pos = [np.zeros(2)]
    pose = SE2.identity()
    for k in range(1, t):
        pose = pose @ SE2(true[k])
        pos.append(np.asarray(pose.translation()))
    z = SE2.exp(jnp.asarray(u + rng.normal(size=u.shape) * 0.05)).data
    gps = np.stack(pos) + rng.normal(size=(t, 2)) * 0.5
    w = np.zeros(t)
    w[0] = 1.0
    return {"z": jnp.asarray(z), "gps": jnp.asarray(gps), "w": jnp.asarray(w)}


def test_incremental_step_solves_the_window_system_at_its_linearization_point():
    """After every incremental update (relinearised or not) the estimate is
    ``lin ⊕ Δ`` with Δ the Gauss–Newton step of the window system at ``lin`` (prior
    included), built independently by the dense system assembly: the cached
    elimination, the shift and the marginalisation by message are exact."""
    t, k = 14, 5
    data = _se2_stream(t)
    d0 = jax.tree.map(lambda a: a[0], data)
    sm = FixedLagSmoother(
        {"pose": SE2.identity()}, d0, window=k, motion=_se2_motion, unary=_se2_unary,
        relinearize_threshold=0.05,
    )

    @jax.jit
    def step(sm, dj):
        sm = sm.update({"pose": sm.latest()["pose"] @ SE2(dj["z"])}, dj)
        lin = sm.linearization_point()
        (h, g, _), _ = sm._system(lin)
        delta = jnp.linalg.solve(sm._regularised(h), -g)
        return sm, jax.vmap(sm._minus)(sm.states, lin).reshape(-1), delta

    relinearised = 0
    for j in range(t):
        sm, got, delta = step(sm, jax.tree.map(lambda a: a[j], data))
        relinearised += int(sm.iterations)
        np.testing.assert_allclose(got, delta, atol=1e-9, rtol=0)
    assert 0 < relinearised < t  # both paths: cached elimination and re-linearisation



def test_relinearize_skip_checks_the_threshold_every_nth_update():
    """Threshold 0 and guesses off the solution: every check re-linearises, so
    ``iterations`` is 1 exactly at updates n, 2n, ... (iSAM2's relinearizeSkip); linear
    factors make the estimate exact at any linearisation point (the batch solution)."""
    t, k, n = 8, 4, 3
    data = _linear_stream(t)
    step = jax.jit(lambda s, d: s.update({"p": s.latest()["p"] + 1.0}, d))
    sm = _smoother(k, relinearize_threshold=0.0, relinearize_skip=n)
    its = []
    for j in range(t):
        sm = step(sm, jax.tree.map(lambda a, j=j: a[j], data))
        its.append(int(sm.iterations))
    assert its == [int((j + 1) % n == 0) for j in range(t)]
    _, mean = _batch(data, t)
    np.testing.assert_allclose(sm.states["p"], mean.reshape(t, 2)[-k:], atol=1e-9)

@pytest.mark.slow
def test_incremental_relinearising_tracks_gauss_newton():
    """With a small threshold the incremental smoother re-linearises and stays close to
    Gauss–Newton to convergence; never re-linearising (threshold ∞) is further off."""
    t, k = 30, 6
    data = _se2_stream(t, seed=1)
    first = {"pose": SE2.identity()}
    steps = ex.Steps(data, first, None, lambda x, d: {"pose": x["pose"] @ SE2(d["z"])})

    def make(**kw):
        d0 = jax.tree.map(lambda a: a[0], data)
        return FixedLagSmoother(
            first, d0, window=k, motion=_se2_motion, unary=_se2_unary, **kw
        )

    ref = np.asarray(ex.run(make(max_iterations=50), steps).trajectory["pose"].log().data)
    err = {}
    for th in (float("inf"), 0.01):
        res = ex.run(make(relinearize_threshold=th), steps)
        err[th] = np.abs(np.asarray(res.trajectory["pose"].log().data) - ref).max()
    assert err[0.01] < 0.1 * err[float("inf")] and err[0.01] < 5e-3, err


# ---------------------------------------------------------------- the kept linearisation
@pytest.mark.parametrize("mode", ["chain", "dense", "incremental"])
def test_kept_linearization_equals_a_fresh_one(mode):
    """After every update of a nonlinear (SE2) stream, what the smoother keeps from its
    last linearisation equals the window system assembled again at the linearisation
    point: the marginal covariances (chains: the elimination's recursion) equal the
    blocks of the inverse of the fresh information, and the dense mode's kept systems
    (all factors; those touching slot 0) equal fresh ones."""
    t, k = 12, 4
    data = _se2_stream(t, seed=3)
    d0 = jax.tree.map(lambda a: a[0], data)
    kw = {"relinearize_threshold": 0.05} if mode == "incremental" else {}
    if mode == "dense":  # one (never valid) loop slot: the dense window system
        kw.update(loop=_se2_motion, loop_data=d0, max_loops=1)
    sm = FixedLagSmoother({"pose": SE2.identity()}, d0, window=k, motion=_se2_motion,
                          unary=_se2_unary, **kw)

    @jax.jit
    def step(sm, dj):
        guess = {"pose": sm.latest()["pose"] @ SE2(dj["z"])}
        if sm.chain:
            sm = sm.update(guess, dj)
        else:
            ld = jax.tree.map(lambda a: a[None], dj)
            sm = sm.update(guess, dj, jnp.ones(1, int), jnp.zeros(1, bool), ld)
        (h, _, _), first = sm._system(sm.linearization_point())
        return sm, sm._regularised(h), first, sm.marginal_covariances()

    for j in range(t):
        sm, h, (h1, g1), cov = step(sm, jax.tree.map(lambda a: a[j], data))
        full = np.linalg.inv(np.asarray(h)).reshape(k, 3, k, 3)
        blocks = np.stack([full[i, :, i, :] for i in range(k)])
        valid = np.asarray(sm.valid)
        assert np.isnan(np.asarray(cov)[~valid]).all()
        np.testing.assert_allclose(cov[valid], blocks[valid], rtol=1e-8, atol=1e-14)
        if mode == "dense":
            np.testing.assert_allclose(sm.information(), h, rtol=1e-10, atol=1e-8)
            np.testing.assert_allclose(sm.first_info, h1, rtol=1e-10, atol=1e-8)
            np.testing.assert_allclose(sm.first_grad, g1, rtol=1e-10, atol=1e-8)


@pytest.mark.parametrize("dense", [False, True])
def test_an_update_with_covariances_linearizes_the_factors_once(dense):
    """The traced program of ``update`` followed by ``marginal_covariances`` evaluates
    the motion residual at one place only (its value and forward-mode Jacobian inside
    the Gauss–Newton loop), not again for the marginalisation and the covariances."""
    calls = []

    def motion(xp, x, d):
        calls.append(1)
        return _motion(xp, x, d)

    d0 = {"z": jnp.zeros(2), "w": jnp.zeros(())}
    kw, loops = {}, ()
    if dense:
        kw = {"loop": _motion, "loop_data": d0, "max_loops": 1}
        loops = (jnp.ones(1, int), jnp.zeros(1, bool), jax.tree.map(lambda a: a[None], d0))
    sm = FixedLagSmoother({"p": jnp.zeros(2)}, d0, window=4, motion=motion, unary=_unary, **kw)
    jax.make_jaxpr(lambda s: s.update({"p": jnp.ones(2)}, d0, *loops).marginal_covariances())(sm)
    assert len(calls) == 2  # r = f(0) and jacfwd(f)(0), once each
