"""CHOLMOD through ctypes: solutions against SciPy, and the choice of BLAS it binds to."""

import os
import struct
import subprocess
import sys

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg

from jaxpose.graph import _cholmod as cholmod


def _require_cholmod():
    if not cholmod.available():
        pytest.skip(f"CHOLMOD unavailable: {cholmod.unavailable_reason()}")


def test_blas_is_reported():
    _require_cholmod()
    blas = cholmod.blas()
    assert isinstance(blas, str) and blas and blas != "not loaded"


def test_supernodal_solve_with_dense_blocks_matches_dense_cholesky():
    """A block-arrow matrix whose supernodes (24-wide dense blocks, a dense 60-wide border)
    go through the BLAS kernels CHOLMOD binds to (whichever :func:`cholmod.blas` names)."""
    _require_cholmod()
    rng = np.random.default_rng(3)
    blocks = []
    for _ in range(8):
        g = rng.normal(size=(24, 24))
        blocks.append(g @ g.T + 24 * np.eye(24))
    n = 8 * 24 + 60
    a = np.zeros((n, n))
    a[:192, :192] = scipy.linalg.block_diag(*blocks)
    border = rng.normal(size=(192, 60))
    a[:192, 192:] = border
    a[192:, :192] = border.T
    g = rng.normal(size=(60, 60))
    a[192:, 192:] = g @ g.T + 400 * np.eye(60)
    h = scipy.sparse.csr_matrix(a)
    h.sort_indices()
    b = rng.normal(size=(n, 2))
    x = cholmod.solve(h.data, h.indices, h.indptr, b)
    expected = scipy.linalg.cho_solve(scipy.linalg.cho_factor(a), b)
    np.testing.assert_allclose(x, expected, rtol=1e-10, atol=1e-12)


def test_symbolic_analysis_is_reused_only_for_its_own_pattern():
    """Patterns of the same size and nonzero count, alternated (the cache's fast path
    compares with the last pattern, the checksum path with the others), and new values on
    a cached pattern: every solve equals the dense one."""
    _require_cholmod()
    rng = np.random.default_rng(5)
    n = 40

    def spd(offsets):
        a = 4.0 * np.eye(n)
        for k in offsets:
            v = rng.uniform(0.1, 0.5, n - k)
            a += np.diag(v, k) + np.diag(v, -k)
        return a

    mats = [spd((1, 4)), spd((2, 3)), spd((1, 4)), spd((4, 7)), spd((2, 3))]
    assert len({scipy.sparse.csr_matrix(m).nnz for m in mats[:2]}) == 1  # same nnz
    for a in mats + mats[::-1]:
        h = scipy.sparse.csr_matrix(a)
        h.sort_indices()
        b = rng.normal(size=n)
        np.testing.assert_allclose(cholmod.solve(h.data, h.indices, h.indptr, b),
                                   np.linalg.solve(a, b), rtol=1e-12, atol=1e-12)


_PROBE = (
    "import warnings, numpy as np\n"
    "from jaxpose.graph import _cholmod as c\n"
    "with warnings.catch_warnings(record=True) as w:\n"
    "    warnings.simplefilter('always')\n"
    "    ok = c.available()\n"
    "x = c.solve(np.array([4.0, 1.0, 1.0, 3.0]), np.array([0, 1, 0, 1]), np.array([0, 2, 4]),"
    " np.array([1.0, 2.0]))\n"
    "print(ok, repr(c.blas()), np.allclose(x, np.linalg.solve([[4, 1], [1, 3]], [1, 2])))\n"
    "print('|'.join(str(m.message) for m in w))\n"
)


def _probe(value: str) -> list[str]:
    env = dict(os.environ, JAXPOSE_BLAS=value)
    out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True,
                         text=True, timeout=300, check=True)
    return out.stdout.splitlines()


@pytest.mark.integration
def test_jaxpose_blas_environment_variable():
    """``reference`` keeps cholespy's BLAS; a library that cannot load gives a warning that
    names the variable, and CHOLMOD still solves (with the reference BLAS)."""
    _require_cholmod()
    result, warned = _probe("reference")
    assert result == "True 'reference (JAXPOSE_BLAS=reference)' True"
    assert warned == ""
    result, warned = _probe("/nonexistent/libblas-missing.so")
    assert result.startswith("True \"reference ('/nonexistent/") and result.endswith(" True")
    assert "JAXPOSE_BLAS='/nonexistent/libblas-missing.so' could not be loaded" in warned
    assert "'reference'" in warned


def test_the_cli_notes_a_reference_blas_unless_asked_for(monkeypatch, capsys):
    """`jaxpose pgo` / `ba` say on stderr when CHOLMOD ran on the reference BLAS for want
    of OpenBLAS (3x slower factorisations), not when the user chose it."""
    _require_cholmod()
    from jaxpose.cli import _note_slow_blas

    monkeypatch.setattr(cholmod, "_BLAS", "reference (no system OpenBLAS found)")
    assert cholmod.slow_blas() == "reference (no system OpenBLAS found)"
    _note_slow_blas("jaxpose pgo")
    err = capsys.readouterr().err
    assert err.startswith("jaxpose pgo: note: CHOLMOD ran on the reference (no system "
                          "OpenBLAS found) BLAS") and "libopenblas0" in err
    for chosen in ("reference (JAXPOSE_BLAS=reference)", "libopenblas.so.0"):
        monkeypatch.setattr(cholmod, "_BLAS", chosen)
        assert cholmod.slow_blas() is None
        _note_slow_blas("jaxpose pgo")
        assert capsys.readouterr().err == ""


def test_without_zeros_drops_exact_zeros_only_when_there_are_many():
    """The pruned CSR is the same matrix with a smaller pattern; below PRUNE_FRACTION the
    arrays come back untouched (no copy, no new pattern to analyse)."""
    from jaxpose.graph import _linear

    rng = np.random.default_rng(7)
    n = 30
    a = np.diag(rng.uniform(2.0, 3.0, n))
    for i, j in rng.integers(0, n, size=(40, 2)):
        if i != j:
            a[i, j] = a[j, i] = rng.uniform(-0.2, 0.2)
    h = scipy.sparse.csr_matrix(a)
    h.sort_indices()
    few = h.data.copy()
    few[np.flatnonzero(h.indices != np.repeat(np.arange(n), np.diff(h.indptr)))[:1]] = 0.0
    assert np.mean(few == 0) < _linear.PRUNE_FRACTION
    out = _linear.without_zeros(few, h.indices, h.indptr)
    assert all(x is y for x, y in zip(out, (few, h.indices, h.indptr), strict=True))

    rows = np.repeat(np.arange(n), np.diff(h.indptr))
    upper = np.flatnonzero(h.indices > rows)
    dropped = a.copy()  # half the off-diagonal pairs zero, still stored (a zero weight)
    dropped[rows[upper[::2]], h.indices[upper[::2]]] = 0.0
    dropped[h.indices[upper[::2]], rows[upper[::2]]] = 0.0
    many = dropped[rows, h.indices]
    off = np.flatnonzero(many == 0)
    assert off.size == 2 * upper[::2].size
    data, indices, indptr = _linear.without_zeros(many, h.indices, h.indptr)
    assert data.size == h.nnz - off.size and np.all(data != 0)
    assert indices.dtype == h.indices.dtype and indptr.dtype == h.indptr.dtype
    pruned = scipy.sparse.csr_matrix((data, indices, indptr), shape=(n, n)).toarray()
    np.testing.assert_array_equal(pruned, dropped)
    b = rng.normal(size=n)
    np.testing.assert_allclose(_linear._cholmod_solve(many, h.indices, h.indptr, b),
                               np.linalg.solve(dropped, b), rtol=1e-12, atol=1e-12)


def _grid_with_random_edges(k: int, extra: int, seed: int = 0) -> scipy.sparse.csr_matrix:
    """Laplacian + 0.1·I of a k×k grid plus ``extra`` random long edges (the sparsity of
    a pose graph with random loop closures), SPD, sorted CSR."""
    n = k * k
    idx = np.arange(n).reshape(k, k)
    rng = np.random.default_rng(seed)
    a, b = rng.integers(0, n, extra), rng.integers(0, n, extra)
    rows = np.concatenate([idx[:, :-1].ravel(), idx[:-1, :].ravel(), a[a != b]])
    cols = np.concatenate([idx[:, 1:].ravel(), idx[1:, :].ravel(), b[a != b]])
    adj = scipy.sparse.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    adj = ((adj + adj.T) > 0).astype(float)
    mat = (scipy.sparse.diags(np.asarray(adj.sum(1)).ravel() + 0.1) - adj).tocsr()
    mat.sort_indices()
    return mat


def test_metis_ordering_replaces_cholmods_where_it_saves_flops(monkeypatch):
    """Above METIS_FLOPS the analysis also orders with METIS and keeps it where it needs
    fewer than METIS_GAIN times the flops of CHOLMOD's choice (a grid with random long
    edges: 3.5e6 → 2.5e6); the solution is the same, and CHOLMOD's method settings are
    restored after the extra analysis."""
    _require_cholmod()
    lib = cholmod._load()
    assert lib.can_reorder  # the documented method defaults were found in cholmod_common
    mat = _grid_with_random_edges(40, 200)
    b = np.linspace(-1.0, 2.0, mat.shape[0])
    want = scipy.sparse.linalg.spsolve(mat.tocsc(), b)
    flops = {}
    for name, threshold in (("cholmod", np.inf), ("metis", 0.0)):
        monkeypatch.setattr(cholmod, "METIS_FLOPS", threshold)
        lib.clear()
        x = lib.solve(mat.data, mat.indices.astype(np.int32), mat.indptr.astype(np.int32), b)
        np.testing.assert_allclose(x, want, rtol=1e-10, atol=1e-12)
        (flops[name],) = lib.flops.values()
        raw = lib.common.raw
        assert struct.unpack_from("i", raw, cholmod._NMETHODS)[0] == 0
        assert struct.unpack_from("i", raw, cholmod._METHODS + cholmod._ORDERING)[0] == 1
    assert flops["metis"] < cholmod.METIS_GAIN * flops["cholmod"], flops
    lib.clear()
