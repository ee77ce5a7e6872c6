"""Loops compiled whole: the LAPACK-free Cholesky of small dense systems, the dense
matrix gathered from CSR values, the probe of the XLA flags, and the ``jaxpose pgo``
process that sets them (a solve with them in effect = the LAPACK solve).

References are NumPy's dense solve, SciPy's CSR ``toarray`` and this process's own solve
(LAPACK; no flags here), never the code under test."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

from jaxpose import _compile, cli
from jaxpose.graph import _linear as linear
from jaxpose.graph import _pgo as pgo
from jaxpose.io import read_g2o

from .conftest import data_file


def _spd(n: int, seed: int, dtype=np.float64) -> np.ndarray:
    m = np.random.default_rng(seed).normal(size=(n, n))
    return (m @ m.T + 0.1 * np.eye(n)).astype(dtype)


@pytest.mark.parametrize("n", [1, 5, 16, 17, 30, 54, 64])
def test_cholesky_solve_loops_matches_numpy(n):
    a, b = _spd(n, n), np.random.default_rng(100 + n).normal(size=n)
    x = jax.jit(linear.cholesky_solve_loops)(a, b)
    want = np.linalg.solve(a, b)
    np.testing.assert_allclose(x, want, rtol=0, atol=1e-11 * np.abs(want).max() * n)
    # segments of other sizes (one column, everything at once) give the same solution
    for segment in (1, n):
        np.testing.assert_allclose(linear.cholesky_solve_loops(a, b, segment), x, rtol=1e-12,
                                   atol=1e-12 * np.abs(want).max())


def test_cholesky_solve_loops_matrix_right_hand_side():
    a, b = _spd(20, 3), np.random.default_rng(4).normal(size=(20, 3))
    np.testing.assert_allclose(jax.jit(linear.cholesky_solve_loops)(a, b),
                               np.linalg.solve(a, b), rtol=0, atol=1e-10)


def test_cholesky_solve_loops_float32_and_vmap():
    a = np.stack([_spd(12, s, np.float32) for s in range(3)])
    b = np.random.default_rng(7).normal(size=(3, 12)).astype(np.float32)
    x = jax.jit(jax.vmap(linear.cholesky_solve_loops))(a, b)
    assert x.dtype == jnp.float32
    want = np.linalg.solve(a.astype(np.float64), b.astype(np.float64)[..., None])[..., 0]
    np.testing.assert_allclose(x, want, rtol=2e-3, atol=2e-3 * np.abs(want).max())


@pytest.mark.parametrize("diagonal", [[1.0, -1.0, 2.0], [1.0, 0.0, 2.0]])
def test_cholesky_solve_loops_not_positive_definite_is_not_finite(diagonal):
    # as JAX's LAPACK Cholesky: no silent number (the LM loop rejects a non-finite step)
    x = linear.cholesky_solve_loops(jnp.diag(jnp.asarray(diagonal)), jnp.ones(3))
    assert not np.any(np.isfinite(np.asarray(x)[1:]))


def test_densify_is_the_csr_matrix():
    graph = pgo.pose_graph_problem(read_g2o(data_file("pose3example.txt")))
    st = graph.structure
    data = np.random.default_rng(3).normal(size=st.nnz)
    want = sp.csr_matrix((data, st.csr_indices, st.csr_indptr), (st.size, st.size)).toarray()
    index = jax.jit(linear.dense_index, static_argnums=2)(st.csr_indices, st.csr_indptr,
                                                          st.size)
    np.testing.assert_array_equal(linear.densify(jnp.asarray(data), index, st.size), want)


def test_this_process_has_no_whole_loops():
    if "xla_backend_extra_options" in os.environ.get("XLA_FLAGS", ""):
        pytest.skip("XLA_FLAGS sets backend options for this test run")
    assert not _compile.loops_compile_whole()


def test_use_whole_loops_keeps_the_users_extra_options(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_extra_options=a=1")
    _compile.use_whole_loops()
    assert os.environ["XLA_FLAGS"] == "--xla_backend_extra_options=a=1"
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/nowhere")
    _compile.use_whole_loops()
    assert os.environ["XLA_FLAGS"] == "--xla_dump_to=/nowhere " + _compile.WHOLE_LOOP_FLAGS


def test_cli_sets_the_flags_only_as_the_processs_command(monkeypatch, tmp_path):
    src = str(data_file("pose2example.txt"))
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert cli.main(["pgo", src, "--quiet"]) == 0  # called from Python: environment kept
    assert "XLA_FLAGS" not in os.environ
    monkeypatch.setattr(sys, "argv", ["jaxpose", "pgo", src, "--quiet"])
    assert cli.main() == 0
    assert os.environ["XLA_FLAGS"] == _compile.WHOLE_LOOP_FLAGS


_CHILD = """
import json, sys
from jaxpose import _compile
_compile.use_whole_loops()
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
from jaxpose.graph import _pgo as pgo
from jaxpose.io import read_g2o
from jaxpose.graph import _solve
out = {"whole": _compile.loops_compile_whole()}
tiny = pgo.pose_graph_problem(read_g2o(sys.argv[1]))
out["without_lapack"] = [  # verbose prints from the loop: a host call keeps it split
    _solve._GraphPath(tiny, "dense", 600, _solve.Damping(), _solve.PCG(), None, None,
                      verbose).dense_loops for verbose in (False, True)]
for path in sys.argv[1:]:
    problem = pgo.pose_graph_problem(read_g2o(path))
    run = jax.jit(lambda p: pgo.solve_from_start(p, "auto")[0],
                  compiler_options=_compile.compile_options())
    text = run.lower(problem).compile().as_text()
    sol = run(problem)
    out[path] = {"loop_in_entry": " while(" in _compile._entry(text),
                 "cost": float(sol.cost), "iterations": int(sol.iterations),
                 "poses": np.asarray(sol.variables["pose"].data).tolist()}
problem = pgo.pose_graph_problem(read_g2o(sys.argv[-1]), dtype=jax.numpy.float32)
out["float32"] = float(jax.jit(lambda p: pgo.solve_from_start(p, "auto")[0].cost,
                               compiler_options=_compile.compile_options())(problem))
_compile.compile_options = dict  # XLA's newer fusion emitters keep the probe's scatter apart
_compile.loops_compile_whole.cache_clear()
out["whole_with_default_options"] = _compile.loops_compile_whole()
print(json.dumps(out))
"""


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="whole loops are XLA:CPU's")
def test_solves_with_whole_loops_equal_the_lapack_solves():
    """A process with the flags compiles (with ``compile_options``, as the CLI) the LM loop
    of the tiny shared graphs whole (no loop left in the program's entry) and reaches this
    process's solution. One SE2 and one SE3 graph (a second SE3 graph compiled the same
    program again: ~10 s of the default run)."""
    paths = [str(data_file(n)) for n in ("pose2example.txt", "tinyGrid3D.g2o")]
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    proc = subprocess.run([sys.executable, "-c", _CHILD, *paths], capture_output=True,
                          text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    child = json.loads(proc.stdout.strip().splitlines()[-1])
    assert child["whole"] is True
    assert child["whole_with_default_options"] is False
    assert child["without_lapack"] == [True, False]
    for path in paths:
        problem = pgo.pose_graph_problem(read_g2o(path))
        run = jax.jit(lambda p: pgo.solve_from_start(p, "auto")[0],
                      compiler_options=_compile.compile_options())
        assert " while(" in _compile._entry(run.lower(problem).compile().as_text())
        here, there = run(problem), child[path]
        assert not there["loop_in_entry"], path
        assert there["iterations"] == int(here.iterations)
        np.testing.assert_allclose(there["cost"], float(here.cost), rtol=1e-10)
        np.testing.assert_allclose(there["poses"], here.variables["pose"].data, rtol=0,
                                   atol=1e-8)
    # float32 (the last graph, tinyGrid3D): the float64 minimum to float32's resolution
    np.testing.assert_allclose(child["float32"], float(here.cost), rtol=1e-5)
