"""jaxpose.sharding: sharded runs equal unsharded ones.

The multi-device checks run in a subprocess started with
``XLA_FLAGS=--xla_force_host_platform_device_count=4 JAX_PLATFORMS=cpu`` (the flag must be
set before JAX starts), executing this file as a script; it prints one JSON line of
results that the test asserts on. Workloads are bench/sharding.py's: Lie ops on a sharded
batch (and their gradients), vmapped least-squares pose-graph loops (XLA partitioner),
vmapped factor-graph solves (``jaxpose.graph.solve``, per-device programs), an EKF over
many sequences with a padded batch (float64, so sharded and unsharded agree to round-off
and iteration counts are identical). The compiled programs' collectives are checked too:
a partitioned solver loop may all-reduce its loop condition but never gathers the batch.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
TAG = "SHARDING-CHECK "


def _worker() -> dict:
    """Runs on 4 simulated CPU devices (see the module docstring)."""
    jax.config.update("jax_enable_x64", True)
    from jax.sharding import PartitionSpec as P

    import jaxpose as jp
    from bench import sharding as bs
    from jaxpose.sharding import batch_mesh, pad_batch, replicate, shard_batch, shard_vmap

    out: dict = {"devices": len(jax.devices())}
    mesh = batch_mesh()

    def spread(tree):
        return [len(x.sharding.device_set) for x in jax.tree.leaves(tree)]

    def collectives(hlo: str) -> dict:
        ops = re.findall(r"\b(all-reduce|all-gather|all-to-all|collective-permute|"
                         r"reduce-scatter)(?:-start)?\(", hlo)
        return {op: ops.count(op) for op in set(ops)}

    # 1. Lie ops over a sharded batch of groups: data placement + plain jit.
    a, b = bs.lie_inputs(64, np.float64)
    X = jp.se3(a).exp()
    Xs = shard_batch(X, mesh)
    out["group_spec"] = str(Xs.data.sharding.spec)
    f = jax.jit(lambda X, b: (X @ jp.se3(b).exp()).log().data)
    ys, y1 = f(Xs, shard_batch(b, mesh)), f(X, b)
    out["lie"] = dict(diff=bs.compare(ys, y1)[0], spread=spread(ys))
    # Gradients through shard_vmap equal those of vmap.
    g = jax.grad(lambda a, b: jnp.sum(bs.lie_fn(a, b) ** 2))
    gs, g1 = shard_vmap(g, mesh)(a, b), jax.vmap(g)(a, b)
    out["lie_grad"] = dict(diff=bs.compare(gs, g1)[0], spread=spread(gs))

    # 2. Eight pose-graph loops solved by vmap(least_squares) (LM, Cholesky), XLA's
    #    partitioner ("partition"; lineax fails inside shard_map). The compiled program
    #    must keep the problems on their devices: the only collectives are all-reduces
    #    (of the loop condition), no all-gather / all-to-all of the batch. Per device the
    #    batched Cholesky stays below jaxlib's threshold for splitting it over the CPU
    #    thread pool (see bench/sharding.py: that split can deadlock on simulated devices).
    meas, init = bs.loop_inputs(8, np.float64, poses=6)
    solve = shard_vmap(lambda m, i: bs.loop_solve(m, i, "cholesky"), mesh)
    compiled = solve.lower(meas, init).compile()
    rs = compiled(meas, init)
    r1 = jax.jit(jax.vmap(bs.loop_solve))(meas, init)
    diff, ints = bs.compare(rs, r1)
    out["lsq"] = dict(diff=diff, int_diff=ints, status=np.asarray(rs[3]).tolist(),
                      shape=list(rs[0].shape), cost=np.asarray(rs[1]).tolist(),
                      collectives=collectives(compiled.as_text()), spread=spread(rs))

    # 2b. Eight pose graphs through jaxpose.graph.solve, per-device programs (shard_map):
    #     no communication at all (padding, checked with the EKF below, would add a
    #     reshuffle of the outputs).
    base, (ginit, gmeas) = bs.graph_inputs(8, np.float64, poses=8)
    gfn = bs.graph_solver(base, "cholesky")
    gsolve = shard_vmap(gfn, mesh, method="shard_map")
    compiled = gsolve.lower(ginit, gmeas).compile()
    gs, g1 = compiled(ginit, gmeas), jax.jit(jax.vmap(gfn))(ginit, gmeas)
    diff, ints = bs.compare(gs, g1)
    out["pgo"] = dict(diff=diff, int_diff=ints, status=np.asarray(gs[3]).tolist(),
                      shape=list(gs[0].shape), iterations=np.asarray(gs[2]).tolist(),
                      collectives=collectives(compiled.as_text()))

    # 2c. The same graphs with CHOLMOD (a host callback) under shard_map: no collective
    #     either ("partition" would gather the batch's sparse systems for the callback)
    def sparse_one(init, meas):
        import equinox as eqx

        from jaxpose.graph import default_stopping, solve
        g = eqx.tree_at(lambda g: g.variables["pose"], base, jp.SE2(init).normalize())
        g = eqx.tree_at(lambda g: g.factors[0].data, g, jp.SE2(meas).normalize())
        sol = solve(g, linear_solver="sparse", stopping=default_stopping(50))
        return sol.variables["pose"].data, sol.cost, sol.iterations, sol.status

    compiled = shard_vmap(sparse_one, mesh, method="shard_map").lower(ginit, gmeas).compile()
    diff, ints = bs.compare(compiled(ginit, gmeas), g1)
    out["pgo_sparse"] = dict(diff=diff, int_diff=ints,
                             collectives=collectives(compiled.as_text()))

    # 3. An EKF over ten sequences, explicit per-device programs (shard_map), shared
    #    (replicated) inputs through in_axes=None.
    us, ys_ = bs.ekf_inputs(10, np.float64, steps=12)
    us_shared = replicate(jnp.asarray(us[0]), mesh)
    run = lambda u, y: bs.ekf_fn(u, y)
    es = shard_vmap(run, mesh, in_axes=(None, 0), method="shard_map")(us_shared, ys_)
    e1 = jax.jit(jax.vmap(run, in_axes=(None, 0)))(us[0], ys_)
    out["ekf"] = dict(diff=bs.compare(es, e1)[0], shape=list(es[0].shape))
    padded, n = pad_batch({"a": jnp.arange(6.0)}, 4)
    out["pad"] = [np.asarray(padded["a"]).tolist(), n]

    # 4. Bad input.
    errors = []
    for bad in (lambda: shard_batch(jnp.zeros((6, 3)), mesh),
                lambda: batch_mesh(5),
                lambda: shard_batch({"a": jnp.zeros((4, 2)), "b": jnp.zeros((8,))}, mesh)):
        try:
            bad()
            errors.append(None)
        except ValueError as err:
            errors.append(str(err))
    out["errors"] = errors
    out["replicated_spec"] = str(us_shared.sharding.spec) if hasattr(
        us_shared.sharding, "spec") else "?"
    assert out["replicated_spec"] == str(P())
    return out


@pytest.fixture(scope="module")
def four_devices() -> dict:
    env = dict(os.environ)
    # the session's flags (tests/conftest.py's probed fast-compile options) minus any
    # device count of its own, then ours
    inherited = [f for f in env.get("XLA_FLAGS", "").split()
                 if not f.startswith("--xla_force_host_platform_device_count")]
    env["XLA_FLAGS"] = " ".join([*inherited, "--xla_force_host_platform_device_count=4"])
    env["JAX_PLATFORMS"] = "cpu"
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run(
        [sys.executable, str(Path(__file__).resolve())], cwd=ROOT, env=env,
        capture_output=True, text=True, timeout=900,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(TAG)]
    assert proc.returncode == 0 and lines, proc.stderr[-4000:]
    return json.loads(lines[-1][len(TAG):])


def test_four_simulated_devices_lie_ops_equal_unsharded(four_devices):
    r = four_devices
    assert r["devices"] == 4
    assert r["group_spec"] == str(jax.sharding.PartitionSpec("batch"))
    assert r["lie"]["spread"] == [4] and r["lie"]["diff"] < 1e-13
    assert r["lie_grad"]["spread"] == [4] and r["lie_grad"]["diff"] < 1e-12


def test_four_simulated_devices_least_squares_and_ekf_equal_unsharded(four_devices):
    r = four_devices
    lsq = r["lsq"]
    assert lsq["shape"] == [8, 6, 4] and lsq["spread"] == [4] * 4
    assert lsq["status"] == [0] * 8  # every loop converged
    assert 0 < max(lsq["cost"]) < 1e-2  # noisy loops: small but non-zero residual cost
    assert lsq["diff"] < 1e-10 and lsq["int_diff"] == 0  # same iterates, same counts
    assert set(lsq["collectives"]) == {"all-reduce"}, lsq["collectives"]
    pgo = r["pgo"]
    assert pgo["shape"] == [8, 8, 4]
    assert pgo["status"] == [0] * 8 and min(pgo["iterations"]) >= 2
    assert pgo["diff"] < 1e-10 and pgo["int_diff"] == 0
    assert pgo["collectives"] == {}, pgo["collectives"]
    sparse = r["pgo_sparse"]  # CHOLMOD on the host, against the dense solves
    assert sparse["diff"] < 1e-10 and sparse["int_diff"] == 0
    assert sparse["collectives"] == {}, sparse["collectives"]
    assert r["ekf"]["shape"] == [10, 12, 4] and r["ekf"]["diff"] < 1e-10
    assert r["pad"] == [[0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 5.0, 5.0], 6]


def test_four_simulated_devices_bad_input(four_devices):
    e = four_devices["errors"]
    assert "not a multiple of the 4 devices" in e[0] and "pad_batch" in e[0]
    assert "batch_mesh(devices)" in e[1] and "[1, 4]" in e[1]
    assert "leading axes disagree" in e[2]


# ----------------------------------------------------------------------------------
# In this process (one device): padding, the one-device mesh, errors.
# ----------------------------------------------------------------------------------
def test_single_device_equals_vmap_and_bad_input():
    from jaxpose.sharding import batch_mesh, batch_sharding, pad_batch, shard_batch, shard_vmap

    mesh = batch_mesh(1)
    assert batch_sharding(mesh).spec == jax.sharding.PartitionSpec("batch")
    x = jnp.arange(12.0, dtype=jnp.float32).reshape(3, 4)
    fn = lambda v, s: jnp.sin(v) * s
    got = shard_vmap(fn, mesh, in_axes=(0, None))(x, 2.0)
    np.testing.assert_array_equal(got, jax.vmap(fn, in_axes=(0, None))(x, 2.0))
    assert got.dtype == jnp.float32
    assert shard_batch({"x": x}, mesh)["x"].shape == (3, 4)
    with pytest.raises(ValueError, match="scalar leaf"):
        pad_batch({"x": x, "s": jnp.float32(1.0)}, 2)
    with pytest.raises(ValueError, match=r"pad_batch\(multiple\)"):
        pad_batch(x, 0)
    with pytest.raises(TypeError, match=r"pad_batch\(multiple\): expected an int"):
        pad_batch(x, 2.5)  # was padded to a multiple of 2
    with pytest.raises(ValueError, match=r"in_axes\): entries must be 0 or None"):
        shard_vmap(fn, mesh, in_axes=(1, None))(x, 2.0)
    with pytest.raises(ValueError, match=r"method"):
        shard_vmap(fn, mesh, method="pmap")
    with pytest.raises(TypeError, match="mesh: expected a jax.sharding.Mesh"):
        shard_batch(x, mesh="cpu")
    with pytest.raises(ValueError, match="axis_name"):
        batch_sharding(mesh, "model")


def test_shard_vmap_arguments_as_vmap_takes_them_or_a_clear_error():
    """NumPy integer in_axes and an empty batch work as in vmap (they failed inside vmap
    and in pad_batch); keyword arguments, disagreeing batch sizes and bool entries get
    errors naming shard_vmap and the argument; batch_mesh refuses a bool (it built a
    one-device mesh) and non-devices; pad_batch keeps NumPy as NumPy when it pads."""
    from jaxpose.sharding import batch_mesh, pad_batch, shard_vmap

    mesh = batch_mesh(1)
    x = jnp.arange(12.0).reshape(3, 4)
    fn = lambda v, s: jnp.sin(v) * s  # noqa: E731
    want = jax.vmap(fn, in_axes=(0, None))(x, 2.0)
    np.testing.assert_array_equal(
        shard_vmap(fn, mesh, in_axes=(np.int64(0), None))(x, 2.0), want)
    assert shard_vmap(fn, mesh, in_axes=(0, None))(x[:0], 2.0).shape == (0, 4)
    with pytest.raises(TypeError, match=r"shard_vmap: pass the arguments positionally.*'s'"):
        shard_vmap(fn, mesh)(x, s=2.0)
    with pytest.raises(ValueError, match=r"shard_vmap: .*disagree.*\{0: 3, 1: 2\}"):
        shard_vmap(fn, mesh)(x, x[:2])
    with pytest.raises(ValueError, match=r"shard_vmap\(argument 1\).*scalar leaf"):
        shard_vmap(fn, mesh)(x, jnp.float32(2.0))
    with pytest.raises(ValueError, match=r"shard_vmap\(in_axes\): entries must be 0 or None"):
        shard_vmap(fn, mesh, in_axes=(False, None))(x, 2.0)
    with pytest.raises(ValueError, match=r"at least one argument must be batched"):
        shard_vmap(fn, mesh, in_axes=None)(x, 2.0)
    for bad in (True, 2.0, "cpu"):
        with pytest.raises(TypeError, match=r"batch_mesh\(devices\): expected a device count"):
            batch_mesh(bad)
    with pytest.raises(TypeError, match=r"batch_mesh\(devices\): expected jax devices"):
        batch_mesh([0])
    padded, n = pad_batch({"a": np.arange(3.0)}, 2)
    assert isinstance(padded["a"], np.ndarray) and padded["a"].tolist() == [0, 1, 2, 2]
    assert n == 3


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    print(TAG + json.dumps(_worker()), flush=True)
