"""The smoother's ``status``: a window system no factor pins down (a gauge left free)
used to return the guesses as the estimate with nothing to tell it from a solve."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.results import Results
from jaxpose.smoothing import FixedLagSmoother, PackedSmoother


def _motion(xp, x, d):
    return x["p"] - xp["p"] - d["u"]


def _unary(x, d):
    return d["w"] * (x["p"] - d["z"])


def _range(x, d):  # nonlinear: one Gauss-Newton step does not solve it
    return jnp.atleast_1d(jnp.sqrt(jnp.sum(x["p"] ** 2) + 1.0) - d["z"][0])


X0 = {"p": jnp.zeros(2)}
D0 = {"u": jnp.zeros(2), "z": jnp.zeros(2), "w": jnp.zeros(())}


def _data(w):
    return {"u": jnp.ones(2), "z": jnp.array([3.0, 0.0]), "w": jnp.asarray(w, float)}


def _stream(sm, w, steps=4):
    guesses = [{"p": jnp.array([5.0 * t, -3.0])} for t in range(steps)]
    for g in guesses:
        sm = sm.update(g, _data(w))
    return sm, guesses


@pytest.mark.parametrize("mode", [{}, {"relinearize_threshold": 0.1}, {"max_loops": 1}])
def test_free_gauge_is_non_finite_and_keeps_the_guess(mode):
    if mode.get("max_loops"):
        mode = dict(mode, loop=_motion, loop_data=D0)
    sm = FixedLagSmoother(X0, D0, window=3, motion=_motion, unary=_unary, **mode)
    if mode.get("max_loops"):
        sm, guesses = sm, [{"p": jnp.array([5.0 * t, -3.0])} for t in range(4)]
        for g in guesses:
            sm = sm.update(g, _data(0.0), jnp.array([1]), jnp.array([False]),
                           {k: v[None] for k, v in D0.items()})
    else:
        sm, guesses = _stream(sm, 0.0)
    assert int(sm.status) == Results.NON_FINITE and sm.status_name == "non_finite"
    np.testing.assert_array_equal(sm.latest()["p"], guesses[-1]["p"])
    # a unary factor on every state determines the window; the problem is linear, so
    # marginalisation is exact and the newest state is the batch least-squares one
    good, _ = _stream(FixedLagSmoother(X0, D0, window=3, motion=_motion, unary=_unary,
                                       **{k: v for k, v in mode.items()
                                          if k == "relinearize_threshold"}), 1.0)
    assert int(good.status) == Results.CONVERGED
    np.testing.assert_allclose(good.latest()["p"], _batch_newest(4), atol=1e-9)


def _batch_newest(n):
    """numpy lstsq of ``p_t = (3, 0)`` and ``p_t − p_{t−1} = (1, 1)``, t < n."""
    rows, rhs = [], []
    for t in range(n):
        rows.append(np.eye(n)[t])
        rhs.append([3.0, 0.0])
        if t:
            rows.append(np.eye(n)[t] - np.eye(n)[t - 1])
            rhs.append([1.0, 1.0])
    return np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0][-1]


def test_status_under_jit_and_vmap_is_per_stream():
    sm = FixedLagSmoother(X0, D0, window=3, motion=_motion, unary=_unary)
    step = jax.jit(FixedLagSmoother.update)
    batch = jax.tree.map(lambda a: jnp.stack([a, a]), sm)
    weights = jnp.array([0.0, 1.0])
    for t in range(3):
        guess = {"p": jnp.tile(jnp.array([5.0 * t, -3.0]), (2, 1))}
        data = jax.vmap(_data)(weights)
        batch = jax.vmap(step)(batch, guess, data)
    assert batch.status.tolist() == [Results.NON_FINITE, Results.CONVERGED]
    assert Results.name_of(batch.status).tolist() == ["non_finite", "converged"]


def test_max_steps_when_the_budget_runs_out():
    kw = dict(window=3, motion=_motion, unary=_range)
    one = FixedLagSmoother(X0, D0, max_iterations=1, **kw)
    many = FixedLagSmoother(X0, D0, max_iterations=50, **kw)
    for t in range(3):
        g, d = {"p": jnp.array([4.0, 1.0 + t])}, _data(1.0)
        one, many = one.update(g, d), many.update(g, d)
    assert int(one.status) == Results.MAX_STEPS and int(one.iterations) == 1
    assert int(many.status) == Results.CONVERGED and int(many.iterations) > 1


def test_packed_smoother_keeps_the_status():
    sm, _ = _stream(FixedLagSmoother(X0, D0, window=3, motion=_motion, unary=_unary), 0.0)
    back = PackedSmoother(sm).unpack()
    assert int(back.status) == Results.NON_FINITE
    step = jax.jit(PackedSmoother.update)
    packed = step(PackedSmoother(sm), {"p": jnp.zeros(2)}, _data(1.0))
    assert int(packed.unpack().status) == Results.CONVERGED


@pytest.mark.parametrize("threshold", [None, 0.1])
def test_a_step_out_of_a_factors_domain_does_not_poison_later_updates(threshold):
    """z = √p with one measurement 0.05 among 1.0s: the first Gauss–Newton step from the
    guess p = 1 lands at p = −0.9, where √p is NaN. The update kept that NaN
    linearisation (incremental mode: the estimate −0.9 too); marginalised two updates
    later it became a NaN prior, and every update after was non_finite, for good. Now the
    update goes back to the last finite linearisation and the stream recovers."""
    def motion(xp, x, d):
        return x["p"] - xp["p"]

    def unary(x, d):
        return (jnp.sqrt(x["p"]) - d["z"]) / 0.01

    guess = {"p": jnp.ones(1)}
    sm = FixedLagSmoother(guess, {"z": jnp.ones(1)}, window=3, motion=motion, unary=unary,
                          relinearize_threshold=threshold)
    step = jax.jit(FixedLagSmoother.update)
    statuses = []
    for z in [1.0, 1.0, 1.0, 1.0, 0.05, 1.0, 1.0, 1.0, 1.0, 1.0]:
        sm = step(sm, guess, {"z": jnp.array([z])})
        statuses.append(sm.status_name)
        assert np.all(np.isfinite(np.asarray(sm.latest()["p"])))
        assert np.all(np.isfinite(np.asarray(sm.prior_info)))
        assert np.all(np.isfinite(np.asarray(sm.marginal_covariances()[-1])))
    assert statuses[4] == "non_finite"  # honest about the bad update
    assert statuses[:4] == statuses[6:] == ["converged"] * 4 and statuses[-1] == "converged"
    # after the window left the bad measurement: z = 1 everywhere in it, the estimate 1
    np.testing.assert_allclose(np.asarray(sm.latest()["p"]), 1.0, atol=1e-6)


@pytest.mark.parametrize("threshold", [None, 0.1])
def test_a_guess_out_of_a_factors_domain_is_dropped_at_marginalisation(threshold):
    """A finite guess p = −1 for z = √p: the update's first linearisation is NaN, so there
    is no finite one to go back to and the update is non_finite. Marginalising that state
    made the prior NaN for good; its information is now dropped with it (the prior stays
    finite) and the stream converges again once the window has moved past it."""
    def motion(xp, x, d):
        return x["p"] - xp["p"]

    def unary(x, d):
        return (jnp.sqrt(x["p"]) - d["z"]) / 0.01

    sm = FixedLagSmoother({"p": jnp.ones(1)}, {"z": jnp.ones(1)}, window=3, motion=motion,
                          unary=unary, relinearize_threshold=threshold)
    step = jax.jit(FixedLagSmoother.update)
    statuses = []
    for t in range(10):
        guess = {"p": jnp.full(1, -1.0 if t == 4 else 1.0)}
        sm = step(sm, guess, {"z": jnp.ones(1)})
        statuses.append(sm.status_name)
        assert np.all(np.isfinite(np.asarray(sm.prior_info)))
    assert statuses[4] == "non_finite"
    assert statuses[:4] == statuses[-3:] + ["converged"] == ["converged"] * 4, statuses
    np.testing.assert_allclose(np.asarray(sm.latest()["p"]), 1.0, atol=1e-6)
