"""PackedSmoother: an exact round trip, packed streams against the closed-form batch
solution (jit with donation, vmap, derivatives), one compilation per configuration,
bad input."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.smoothing import FixedLagSmoother, PackedSmoother

from .test_fixed_lag import _batch, _linear_stream, _smoother


def _filled(k=3, t=4, **kw):
    """A smoother after ``t`` updates (a full window, marginalised states, loops)."""

    @jax.jit
    def step(sm, d, valid):
        loops = () if sm.chain else (jnp.ones(1, int), valid[None],
                                     jax.tree.map(lambda a: a[None], d))
        return sm.update({"p": sm.latest()["p"]}, d, *loops)

    sm, data = _smoother(k, **kw), _linear_stream(t)
    for j in range(t):
        sm = step(sm, jax.tree.map(lambda a, j=j: a[j], data), jnp.asarray(j % 2 == 1))
    return sm


@pytest.mark.parametrize("kw", [{}, {"dense": True}, {"relinearize_threshold": 0.1}])
def test_round_trip_is_exact(kw):
    sm = _filled(**kw)
    packed = PackedSmoother(sm)
    assert packed.buffer.ndim == 1 and packed.buffer.dtype == jnp.float64
    back = packed.unpack()
    assert jax.tree.structure(back) == jax.tree.structure(sm)
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(sm), strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    assert any(x.dtype == bool for x in jax.tree.leaves(sm))  # the casts are exercised
    assert any(jnp.issubdtype(x.dtype, jnp.integer) for x in jax.tree.leaves(sm))


def test_round_trip_float32():
    x0, d0 = {"p": jnp.zeros(2, jnp.float32)}, {"z": jnp.zeros(2, jnp.float32),
                                               "w": jnp.zeros((), jnp.float32)}
    sm = FixedLagSmoother(x0, d0, window=3, motion=lambda xp, x, d: x["p"] - xp["p"],
                          unary=lambda x, d: x["p"] - d["z"])
    sm = jax.jit(FixedLagSmoother.update)(sm, {"p": jnp.ones(2, jnp.float32)},
                                          {"z": jnp.ones(2, jnp.float32),
                                           "w": jnp.ones((), jnp.float32)})
    packed = PackedSmoother(sm)
    assert packed.buffer.dtype == jnp.float32
    for a, b in zip(jax.tree.leaves(packed.unpack()), jax.tree.leaves(sm), strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("threshold", [None, 0.1])
def test_donated_jitted_stream_equals_batch(threshold):
    t, k = 8, 3
    data = _linear_stream(t)
    traces = []

    def update(p, guess, d):
        traces.append(1)
        return p.update(guess, d)

    step = jax.jit(update, donate_argnums=0)
    packed = PackedSmoother(_smoother(k, relinearize_threshold=threshold))
    for j in range(t):
        d = jax.tree.map(lambda a, j=j: a[j], data)
        packed = step(packed, {"p": packed.unpack().latest()["p"]}, d)
        h, mean = _batch(jax.tree.map(lambda a, j=j: a[: j + 1], data), j + 1)
        np.testing.assert_allclose(packed.unpack().latest()["p"], mean[-2:], atol=1e-9)
    np.testing.assert_allclose(packed.unpack().states["p"], mean.reshape(t, 2)[-k:], atol=1e-9)
    # packed smoothers of one configuration share the layout, hence the compilation
    step(PackedSmoother(_smoother(k, relinearize_threshold=threshold)), {"p": jnp.zeros(2)},
         jax.tree.map(lambda a: a[0], data))
    assert len(traces) == 1


def test_vmap_over_packed_streams():
    t, k = 6, 3
    datas = [_linear_stream(t, seed) for seed in (1, 2)]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *datas)
    packed = eqx.filter_vmap(lambda _: PackedSmoother(_smoother(k)), axis_size=2)(jnp.arange(2))
    assert packed.buffer.shape[0] == 2

    @jax.jit
    @jax.vmap
    def run(p, data):
        def body(p, d):
            p = p.update({"p": p.unpack().latest()["p"]}, d)
            return p, p.unpack().latest()["p"]

        return jax.lax.scan(body, p, data)[1]

    latest = run(packed, stacked)
    for i, data in enumerate(datas):
        _, mean = _batch(data, t)
        np.testing.assert_allclose(latest[i, -1], mean[-2:], atol=1e-9)


def test_derivative_of_the_newest_estimate_matches_the_batch_solution():
    """The newest estimate is linear in the newest measurement: its Jacobian through a
    packed update equals the batch least-squares gain (finite differences of the numpy
    batch solve, exact for a linear map)."""
    t, k = 5, 3
    data = _linear_stream(t)
    packed, step = PackedSmoother(_smoother(k)), jax.jit(PackedSmoother.update)
    for j in range(t - 1):
        packed = step(packed, {"p": jnp.zeros(2)}, jax.tree.map(lambda a, j=j: a[j], data))

    def newest(z):
        d = {"z": z, "w": data["w"][t - 1]}
        return packed.update({"p": jnp.zeros(2)}, d).unpack().latest()["p"]

    jac = jax.jit(jax.jacfwd(newest))(data["z"][t - 1])
    ref = np.zeros((2, 2))
    for c in range(2):
        zp, zm = np.array(data["z"]), np.array(data["z"])
        zp[t - 1, c] += 1.0
        zm[t - 1, c] -= 1.0
        mp = _batch({"z": jnp.asarray(zp), "w": data["w"]}, t)[1][-2:]
        mm = _batch({"z": jnp.asarray(zm), "w": data["w"]}, t)[1][-2:]
        ref[:, c] = (mp - mm) / 2.0
    np.testing.assert_allclose(jac, ref, atol=1e-9)
    # reverse mode cannot pass the solve's while_loop: an error that names the alternative
    with pytest.raises(NotImplementedError, match=r"FixedLagSmoother.update: reverse-mode.*"
                                                  r"jax.jacfwd"):
        jax.jacrev(newest)(data["z"][t - 1])


def test_bad_input():
    with pytest.raises(TypeError, match=r"PackedSmoother\(smoother\): expected a FixedLagSmoother"):
        PackedSmoother({"p": jnp.zeros(2)})
    packed = PackedSmoother(_smoother(3))
    with pytest.raises(TypeError, match="guess"):
        packed.update({"q": jnp.zeros(2)}, {"z": jnp.zeros(2), "w": jnp.zeros(())})


def test_round_trip_keeps_wider_data_exact():
    """A float32 smoother with float64 and int64 step data: every leaf was cast to float32
    (a timestamp 16777217 came back as 16777216, 6378137.3 as 6378137.5, and the packed
    update then solved with the rounded data)."""
    f32 = jnp.float32
    x0 = jnp.zeros(2, f32)
    d0 = {"z": jnp.zeros(2, f32), "stamp": jnp.zeros((), jnp.int64),
          "ecef": jnp.zeros(3, jnp.float64)}
    sm = FixedLagSmoother(x0, d0, window=3, motion=lambda xp, x, d: (x - xp) - d["z"],
                          unary=lambda x, d: x - (d["ecef"][:2] - 6378137.0).astype(x.dtype))
    d = {"z": jnp.ones(2, f32), "stamp": jnp.asarray(16777217, jnp.int64),
         "ecef": jnp.asarray([6378137.3, 6378137.25, 0.0])}
    sm = sm.update(jnp.zeros(2, f32), d)
    packed = PackedSmoother(sm)
    assert packed.buffer.dtype == jnp.float64
    for a, b in zip(jax.tree.leaves(packed.unpack()), jax.tree.leaves(sm), strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(packed.update(x0, d).unpack().latest(),
                                  sm.update(x0, d).latest())


def test_integer_data_beyond_the_buffers_exact_range_raise():
    x0, d0 = jnp.zeros(2, jnp.float32), {"z": jnp.zeros(2, jnp.float32),
                                         "stamp": jnp.zeros((), jnp.int64)}
    sm = FixedLagSmoother(x0, d0, window=3, motion=lambda xp, x, d: x - xp - d["z"])
    d = {"z": jnp.ones(2, jnp.float32), "stamp": jnp.asarray(2**24 + 1, jnp.int64)}
    sm = sm.update(x0, d)
    with pytest.raises(ValueError, match=r"PackedSmoother: the integer data .*\.data\['stamp'\]"
                                         r" holds a value beyond ±16777216"):
        PackedSmoother(sm)
    with pytest.raises(RuntimeError, match=r"holds a value beyond ±16777216"):
        jax.block_until_ready(jax.jit(lambda s: PackedSmoother(s).buffer)(sm))
    ok = FixedLagSmoother(x0, d0, window=3, motion=lambda xp, x, d: x - xp - d["z"])
    for stamp in (2**24, -2**24):  # the limits themselves are exact
        ok = ok.update(x0, {"z": jnp.ones(2, jnp.float32), "stamp": jnp.asarray(stamp)})
    np.testing.assert_array_equal(PackedSmoother(ok).unpack().data["stamp"], ok.data["stamp"])
