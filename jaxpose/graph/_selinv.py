"""Selected entries of the inverse of a sparse SPD matrix (host, numpy + CHOLMOD).

The marginal covariances of a factor graph are blocks of H⁻¹ (H the Gauss–Newton matrix).
:func:`inverse_entries` returns chosen entries ``(H⁻¹)[rows, cols]`` by *selected
inversion* (the Takahashi recurrences, supernodal form): with P H Pᵀ = L Lᵀ (CHOLMOD's
supernodal factor, fill-reducing ordering P), the inverse Σ is computed on the pattern of L
only, supernode by supernode from the last one, as

    Y = L_RK L_KK⁻¹,   Σ_RK = −Σ_RR Y,   Σ_KK = L_KK⁻ᵀ L_KK⁻¹ − Σ_RKᵀ Y

(K: the columns of a supernode, R: its off-diagonal rows; Σ_RR lies on the pattern of L
already computed, because R is a clique of the filled graph). Its cost is of the order of
the factorisation, instead of one pair of triangular solves per column. Entries outside the
pattern of L (e.g. the joint block of two poses far apart in the graph) are computed with
block solves reusing the same factor.

The factor is read from CHOLMOD's ``cholmod_factor`` struct (layout of CHOLMOD 3–5, the
fields below; checked at load by a self-test that rebuilds P A Pᵀ from the factor). When
that is unavailable (no cholespy, a different layout), SciPy's sparse LU solves the
requested columns instead (correct, slower).
"""

from __future__ import annotations

import contextlib
import ctypes
import struct
import threading
from collections.abc import Iterator

import numpy as np
from scipy.linalg.lapack import dtrtri as _trtri

from . import _cholmod as cholmod

# cholmod_factor field offsets (size_t/pointers 8 bytes; int 4): n 0, minor 8, Perm 16,
# nsuper 104, ssize 112, xsize 120, super 144, pi 152, px 160, s 168, is_ll 180,
# is_super 184, itype 192, xtype 196, dtype 200
_FACTOR_BYTES = 208
_SOLVE_A = 0
_CHUNK = 512  # right-hand sides per CHOLMOD solve

_CHECKED: bool | None = None
_BLAS_LOCK = threading.Lock()
_SET = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
        "openblas_set_num_threads64_", "openblas_set_num_threads")


def _openblas_handles() -> list[tuple[object, object]]:
    """(set, get) thread-count functions of every OpenBLAS loaded in this process."""
    try:
        with open("/proc/self/maps") as fh:
            paths = sorted({ln.split()[-1] for ln in fh if "openblas" in ln.lower()
                            and ln.split()[-1].startswith("/")})
    except OSError:
        return []
    out = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in _SET:
            get = name.replace("set_num", "get_num")
            if hasattr(lib, name) and hasattr(lib, get):
                out.append((getattr(lib, name), getattr(lib, get)))
                break
    return out


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Run OpenBLAS single-threaded inside the block (restored after).

    The recurrences make many small dense products; OpenBLAS's thread pool spends more
    on hand-offs and spinning than on them (30 ms per 6×6 triangular solve measured on a
    loaded 2-core machine, against 2 µs single-threaded)."""
    with _BLAS_LOCK:
        handles = _openblas_handles()
        old = []
        for set_, get in handles:
            try:
                old.append((set_, int(get())))
                set_(1)
            except (OSError, ValueError, TypeError):
                continue
        try:
            yield
        finally:
            for set_, n in old:
                set_(n)
_CHECK_LOCK = threading.Lock()


class Supernodal:
    """The supernodal factor P A Pᵀ = L Lᵀ as numpy arrays (CHOLMOD's layout).

    ``perm`` (n,): row k of L is row ``perm[k]`` of A; supernode j holds columns
    ``sup[j]:sup[j+1]``, row indices ``rows[pi[j]:pi[j+1]]`` (its own columns first) and
    values ``x[px[j]:]`` column-major with leading dimension ``pi[j+1] − pi[j]``."""

    def __init__(self, n, perm, sup, pi, px, rows, x):
        self.n, self.perm, self.sup, self.pi, self.px, self.rows, self.x = (
            n, perm, sup, pi, px, rows, x)
        self.nsuper = sup.shape[0] - 1

    def block(self, j: int, values: np.ndarray | None = None) -> np.ndarray:
        """(nrows, ncols) values of supernode j (of ``values``, default L)."""
        nr = self.pi[j + 1] - self.pi[j]
        nc = self.sup[j + 1] - self.sup[j]
        v = self.x if values is None else values
        return v[self.px[j] : self.px[j] + nr * nc].reshape(nc, nr).T


def _read(ptr: int, ctype, count: int, dtype) -> np.ndarray:
    if count == 0:
        return np.zeros(0, dtype)
    return np.ctypeslib.as_array(ctypes.cast(ptr, ctypes.POINTER(ctype)), (count,)).astype(
        dtype, copy=True)


def _factor_raw(data: np.ndarray, indices: np.ndarray, indptr: np.ndarray) -> Supernodal | None:
    """CHOLMOD's supernodal factor of the symmetric CSR matrix; None if not SPD.
    Raises OSError if the factor is not of the expected kind."""
    lib = cholmod._load()
    if lib is None:
        raise OSError(f"CHOLMOD is not available ({cholmod.unavailable_reason()})")
    n = indptr.shape[0] - 1
    with lib.lock:
        factor = lib._symbolic(data, indices, indptr)
        lib.lib.cholmod_factorize(ctypes.byref(lib._matrix(data, indices, indptr)), factor,
                                  lib.common)
        raw = ctypes.string_at(factor, _FACTOR_BYTES)
        fn, minor, perm_p = struct.unpack_from("QQQ", raw, 0)
        x_p = struct.unpack_from("Q", raw, 64)[0]
        nsuper, ssize, xsize = struct.unpack_from("QQQ", raw, 104)
        super_p, pi_p, px_p, s_p = struct.unpack_from("QQQQ", raw, 144)
        is_ll, is_super, _, itype, xtype, dtype = struct.unpack_from("iiiiii", raw, 180)
        if fn != n or not (is_ll == 1 and is_super == 1 and itype == 0 and xtype == 1
                           and dtype == 0):
            raise OSError("unexpected cholmod_factor layout")
        if minor < n:
            return None
        i32, f64 = ctypes.c_int32, ctypes.c_double
        out = Supernodal(
            n,
            _read(perm_p, i32, n, np.int64),
            _read(super_p, i32, nsuper + 1, np.int64),
            _read(pi_p, i32, nsuper + 1, np.int64),
            _read(px_p, i32, nsuper + 1, np.int64),
            _read(s_p, i32, ssize, np.int64),
            _read(x_p, f64, xsize, np.float64),
        )
    return out


def _self_test() -> bool:
    """Rebuild P A Pᵀ from the factor of a small random sparse SPD matrix."""
    rng = np.random.default_rng(0)
    n = 40
    a = np.where(rng.random((n, n)) < 0.1, rng.normal(size=(n, n)), 0.0)
    a = a + a.T + np.diag(np.full(n, 8.0))
    rows, cols = np.nonzero(a)
    indptr = np.searchsorted(rows, np.arange(n + 1)).astype(np.int32)
    f = _factor_raw(a[rows, cols].copy(), cols.astype(np.int32), indptr)
    if f is None:
        return False
    lmat = np.zeros((n, n))
    for j in range(f.nsuper):
        r = f.rows[f.pi[j] : f.pi[j + 1]]
        c0, c1 = f.sup[j], f.sup[j + 1]
        blk = f.block(j).copy()
        blk[: c1 - c0] = np.tril(blk[: c1 - c0])
        lmat[np.ix_(r, np.arange(c0, c1))] = blk
    cholmod._load().clear()
    return bool(np.allclose(lmat @ lmat.T, a[np.ix_(f.perm, f.perm)], rtol=1e-12, atol=1e-12))


def supernodal_available() -> bool:
    """True when CHOLMOD's supernodal factor can be read (checked once)."""
    global _CHECKED
    with _CHECK_LOCK:
        if _CHECKED is None:
            try:
                _CHECKED = cholmod.available() and _self_test()
            except (OSError, ValueError):
                _CHECKED = False
        return _CHECKED


def factor(data, indices, indptr) -> Supernodal | None:
    """Supernodal Cholesky factor of SPD A in symmetric CSR (None if A is not SPD)."""
    return _factor_raw(np.ascontiguousarray(data, np.float64),
                       np.ascontiguousarray(indices, np.int32),
                       np.ascontiguousarray(indptr, np.int32))


def selected_inverse(f: Supernodal) -> np.ndarray:
    """Σ = (LLᵀ)⁻¹ on the pattern of L, in the layout of ``f.x`` (module docstring)."""
    with single_threaded_blas():
        return _selected_inverse(f)


def _selected_inverse(f: Supernodal) -> np.ndarray:
    sigma = np.zeros_like(f.x)
    sup, pi, rows = f.sup, f.pi, f.rows
    owner = np.repeat(np.arange(f.nsuper), np.diff(sup))  # supernode of each column
    for k in range(f.nsuper - 1, -1, -1):
        c0, c1 = sup[k], sup[k + 1]
        nc = c1 - c0
        lk = f.block(k)
        ld = np.tril(lk[:nc])
        ldinv, info = _trtri(ld, lower=1)
        if info != 0:
            raise np.linalg.LinAlgError("selected_inverse: singular factor")
        diag = ldinv.T @ ldinv
        out = f.block(k, sigma)  # a view: writes go into sigma
        if lk.shape[0] > nc:
            r = rows[pi[k] + nc : pi[k + 1]]
            y = lk[nc:] @ ldinv
            srr = _gather_block(f, sigma, owner, r)
            s_rk = -srr @ y
            out[nc:] = s_rk
            diag = diag - y.T @ s_rk
        out[:nc] = 0.5 * (diag + diag.T)
    return sigma


def _gather_block(f: Supernodal, sigma: np.ndarray, owner: np.ndarray,
                  r: np.ndarray) -> np.ndarray:
    """Σ[r, r] (symmetric) for sorted rows r on the pattern of L (ancestors computed)."""
    m = r.shape[0]
    out = np.empty((m, m))
    own = owner[r]
    starts = np.flatnonzero(np.r_[True, own[1:] != own[:-1]])
    ends = np.r_[starts[1:], m]
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        j = own[a]
        rj = f.rows[f.pi[j] : f.pi[j + 1]]
        pos = np.searchsorted(rj, r[a:])
        blk = f.block(j, sigma)
        out[a:, a:b] = blk[pos][:, r[a:b] - f.sup[j]]
        out[a:b, b:] = out[b:, a:b].T
    return out


def lookup(f: Supernodal, sigma: np.ndarray, i: np.ndarray,
           j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entries Σ[i, j] (indices of L's ordering) that lie on the pattern of L.

    Returns (values, found): ``found`` is False where (i, j) is outside the pattern."""
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    owner = np.searchsorted(f.sup, lo, side="right") - 1
    seg = np.repeat(np.arange(f.nsuper), np.diff(f.pi))
    keys = seg * f.n + f.rows  # sorted: supernodes ascending, rows ascending within
    want = owner * f.n + hi
    pos = np.searchsorted(keys, want)
    pos_c = np.minimum(pos, keys.shape[0] - 1)
    found = keys[pos_c] == want
    local_row = pos_c - f.pi[owner]
    nrows = f.pi[owner + 1] - f.pi[owner]
    flat = f.px[owner] + (lo - f.sup[owner]) * nrows + local_row
    values = np.where(found, sigma[np.where(found, flat, 0)], 0.0)
    return values, found


def solve_columns(data, indices, indptr, cols: np.ndarray) -> np.ndarray:
    """Columns ``cols`` of A⁻¹ (n, len(cols)), by solves reusing CHOLMOD's factor."""
    lib = cholmod._load()
    data = np.ascontiguousarray(data, np.float64)
    indices = np.ascontiguousarray(indices, np.int32)
    indptr = np.ascontiguousarray(indptr, np.int32)
    n = indptr.shape[0] - 1
    out = np.empty((n, cols.shape[0]))
    if lib is None:
        return _scipy_columns(data, indices, indptr, cols)
    with lib.lock:
        factor_p = lib._symbolic(data, indices, indptr)
        lib.lib.cholmod_factorize(ctypes.byref(lib._matrix(data, indices, indptr)), factor_p,
                                  lib.common)
        if struct.unpack_from("QQ", ctypes.string_at(factor_p, 16))[1] < n:
            return np.full((n, cols.shape[0]), np.nan)
        for s in range(0, cols.shape[0], _CHUNK):
            c = cols[s : s + _CHUNK]
            rhs = np.zeros((c.shape[0], n))  # column-major (n, k)
            rhs[np.arange(c.shape[0]), c] = 1.0
            dense = cholmod._Dense(n, c.shape[0], n * c.shape[0], n, rhs.ctypes.data, None,
                                   cholmod._REAL, cholmod._DOUBLE)
            res = lib.lib.cholmod_solve(_SOLVE_A, factor_p, ctypes.byref(dense), lib.common)
            if not res:
                raise MemoryError("cholmod_solve failed")
            vals = np.ctypeslib.as_array(
                ctypes.cast(res.contents.x, ctypes.POINTER(ctypes.c_double)),
                (c.shape[0] * n,))
            out[:, s : s + _CHUNK] = vals.reshape(c.shape[0], n).T
            lib.lib.cholmod_free_dense(ctypes.byref(res), lib.common)
    return out


def _scipy_columns(data, indices, indptr, cols):
    import scipy.sparse
    import scipy.sparse.linalg

    n = indptr.shape[0] - 1
    mat = scipy.sparse.csc_matrix((data, indices, indptr), shape=(n, n))
    try:
        lu = scipy.sparse.linalg.splu(mat, permc_spec="MMD_AT_PLUS_A",
                                      options={"SymmetricMode": True})
    except RuntimeError:
        return np.full((n, cols.shape[0]), np.nan)
    rhs = np.zeros((n, cols.shape[0]))
    rhs[cols, np.arange(cols.shape[0])] = 1.0
    return lu.solve(rhs)


def inverse_entries(data, indices, indptr, i, j) -> np.ndarray:
    """(A⁻¹)[i, j] for SPD A in symmetric CSR and index arrays i, j (same shape).

    Selected inversion on the supernodal factor where available; entries off the pattern
    of L (and everything, without a readable factor) by solves for their columns. NaN when
    A is not positive definite."""
    i = np.asarray(i, np.int64)
    j = np.asarray(j, np.int64)
    shape = i.shape
    i, j = i.reshape(-1), j.reshape(-1)
    if i.size == 0:
        return np.zeros(shape)
    values = np.zeros(i.shape[0])
    missing = np.ones(i.shape[0], bool)
    if supernodal_available():
        f = factor(data, indices, indptr)
        if f is None:
            return np.full(shape, np.nan)
        sigma = selected_inverse(f)
        iperm = np.empty(f.n, np.int64)
        iperm[f.perm] = np.arange(f.n)
        values, found = lookup(f, sigma, iperm[i], iperm[j])
        missing = ~found
    if missing.any():
        cols, inv = np.unique(j[missing], return_inverse=True)
        block = solve_columns(data, indices, indptr, cols)
        values[missing] = block[i[missing], inv]
    return values.reshape(shape)
