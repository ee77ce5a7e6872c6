"""Host-side sparse Cholesky that reuses its symbolic analysis (CHOLMOD through ctypes).

The ``cholespy`` package (a declared dependency) ships a complete CHOLMOD (supernodal
factorisation, AMD/METIS orderings), but its Python API re-runs the fill-reducing ordering
and the symbolic analysis and then a simplicial factorisation on every call. Levenberg–
Marquardt factorises matrices of one fixed pattern over and over, so this module calls
CHOLMOD's C entry points in that library directly: ``cholmod_analyze`` once per sparsity
pattern (kept in a small cache keyed by the pattern), ``cholmod_factorize`` (numeric only,
supernodal LLᵀ) and ``cholmod_solve`` per call. CHOLMOD orders by the fewest nonzeros in
L (AMD on most pose graphs); for factorisations of more than :data:`METIS_FLOPS` flops the
analysis also tries METIS and keeps whichever needs fewer flops (:data:`METIS_GAIN`).

The ctypes structure layouts are CHOLMOD's public ``cholmod_sparse``/``cholmod_dense``
structs and the leading fields of ``cholmod_common``/``cholmod_factor``; they are checked
when the library is loaded (``cholmod_start``'s documented defaults must read back at their
offsets, and a small SPD and a non-SPD system must solve/fail as expected). On any mismatch
:func:`available` is False and callers use cholespy's public API instead.

Matrices are given as symmetric CSR (full pattern, sorted column indices); CHOLMOD reads
the same arrays as CSC and uses one triangle (``stype = 1``).

BLAS: cholespy's wheel links CHOLMOD against the reference BLAS, whose dense kernels are
what a supernodal factorisation spends its time in (3.3x slower than OpenBLAS on the
sphere2500 Gauss–Newton matrix, one thread). Before loading that library, this module loads
an optimised LP64 BLAS into the global symbol scope, so CHOLMOD's ``dgemm_``/``dsyrk_``/
``dtrsm_``/``dpotrf_`` bind to it: the library named by the environment variable
``JAXPOSE_BLAS`` (a path or soname; ``reference`` keeps cholespy's own), else the system's
OpenBLAS where one is installed (Debian/Ubuntu: ``apt-get install libopenblas0``), set to
one thread unless ``OPENBLAS_NUM_THREADS`` says otherwise (the calls run inside XLA host
callbacks, where idle OpenBLAS threads would spin against XLA's; a second thread gained
under 10 % on sphere2500).
:func:`blas` says which one is in use; the self-test includes a dense block, so a BLAS that
computes wrong results is caught at load.
"""

from __future__ import annotations

import atexit
import ctypes
import ctypes.util
import glob
import importlib.util
import os
import struct
import sys
import threading
import warnings
import zlib
from collections import OrderedDict
from typing import Any

import numpy as np

_SIZE_T, _VOIDP, _INT = ctypes.c_size_t, ctypes.c_void_p, ctypes.c_int
CACHE_SIZE = 4  # sparsity patterns whose symbolic factorisation is kept


class _Sparse(ctypes.Structure):
    _fields_ = [("nrow", _SIZE_T), ("ncol", _SIZE_T), ("nzmax", _SIZE_T), ("p", _VOIDP),
                ("i", _VOIDP), ("nz", _VOIDP), ("x", _VOIDP), ("z", _VOIDP), ("stype", _INT),
                ("itype", _INT), ("xtype", _INT), ("dtype", _INT), ("sorted", _INT),
                ("packed", _INT)]


class _Dense(ctypes.Structure):
    _fields_ = [("nrow", _SIZE_T), ("ncol", _SIZE_T), ("nzmax", _SIZE_T), ("d", _SIZE_T),
                ("x", _VOIDP), ("z", _VOIDP), ("xtype", _INT), ("dtype", _INT)]


# cholmod_common: offsets of leading fields (unchanged since CHOLMOD 1.x) and their defaults
_DEFAULTS = (("d", 0, 0.0), ("d", 8, 1.2), ("d", 16, 1.2), ("Q", 24, 5), ("Q", 32, 8),
             ("d", 40, 40.0), ("i", 48, 1), ("d", 80, 0.8), ("d", 88, 0.1), ("d", 96, 0.05),
             ("Q", 104, 4), ("Q", 112, 16), ("Q", 120, 48), ("i", 144, 3))
_PRINT_OFFSET, _SUPERNODAL_OFFSET, _SUPERNODAL = 144, 48, 2
_REAL, _INT_INDEX, _DOUBLE, _SOLVE_A = 1, 0, 0, 0
# ordering choice: nmethods, selected, and per cholmod_method_struct (168 bytes from 184)
# its flop count and ordering; default methods [GIVEN, AMD, METIS, NESDIS] = [1, 2, 3, 4]
_NMETHODS, _SELECTED, _METHODS, _METHOD_SIZE, _FL, _ORDERING = 168, 176, 184, 168, 8, 132
_METIS = 3

METIS_GAIN = 0.9
"""METIS's ordering replaces CHOLMOD's choice only below this fraction of its flops (the
flop count is a rough proxy of the supernodal factorisation's time: on sphere2500 METIS's
1 % fewer flops took 3 % longer)."""

METIS_FLOPS = 1e8
"""Flop count of a factorisation from which the analysis also tries METIS's nested
dissection when CHOLMOD's own choice (fewest nonzeros in L, usually AMD) is not it, and
keeps the ordering with fewer flops. Below it a second ordering costs more than it can
save. Measured (one factorisation, AMD → METIS): sphere_bignoise_vertex3 28 → 22 ms
(8.6e8 → 5.5e8 flops), sphere2500 with half its loop closures random 325 → 269 ms
(1.33e10 → 1.13e10; CHOLMOD keeps AMD for its 1 % smaller L); sphere2500 itself within
1 % either way; parking-garage (2e7 flops) and the smaller graphs are left to CHOLMOD."""


class _Library:
    """The loaded CHOLMOD and one ``cholmod_common`` (all calls hold ``lock``)."""

    def __init__(self, path: str):
        lib = ctypes.CDLL(path)
        lib.cholmod_start.argtypes = [_VOIDP]
        lib.cholmod_analyze.restype = _VOIDP
        lib.cholmod_analyze.argtypes = [ctypes.POINTER(_Sparse), _VOIDP]
        lib.cholmod_factorize.argtypes = [ctypes.POINTER(_Sparse), _VOIDP, _VOIDP]
        lib.cholmod_solve.restype = ctypes.POINTER(_Dense)
        lib.cholmod_solve.argtypes = [_INT, _VOIDP, ctypes.POINTER(_Dense), _VOIDP]
        lib.cholmod_free_dense.argtypes = [ctypes.POINTER(ctypes.POINTER(_Dense)), _VOIDP]
        lib.cholmod_free_factor.argtypes = [ctypes.POINTER(_VOIDP), _VOIDP]
        lib.cholmod_finish.argtypes = [_VOIDP]
        self.lib = lib
        self.common = ctypes.create_string_buffer(1 << 16)  # sizeof(cholmod_common) < 8 KiB
        if not lib.cholmod_start(self.common):
            raise OSError("cholmod_start failed")
        raw = self.common.raw
        for fmt, off, want in _DEFAULTS:
            if struct.unpack_from(fmt, raw, off)[0] != want:
                raise OSError(f"unexpected cholmod_common layout at offset {off}")
        # the ordering fields are read and set only where they hold their documented
        # defaults (nmethods 0; methods 1–3 AMD, METIS, NESDIS)
        self.can_reorder = struct.unpack_from("i", raw, _NMETHODS)[0] == 0 and all(
            struct.unpack_from("i", raw, _METHODS + k * _METHOD_SIZE + _ORDERING)[0] == k + 1
            for k in (1, 2, 3))
        struct.pack_into("i", self.common, _PRINT_OFFSET, 0)  # failures are reported by value
        # always LLᵀ (supernodal): a non-positive pivot stops it, so "not SPD" is detected
        struct.pack_into("i", self.common, _SUPERNODAL_OFFSET, _SUPERNODAL)
        self.lock = threading.Lock()
        self.cache: OrderedDict[tuple, tuple[np.ndarray, np.ndarray, int]] = OrderedDict()
        self.flops: dict[int, float] = {}  # factor -> flops of its numeric factorisation

    def _matrix(self, data: np.ndarray, indices: np.ndarray, indptr: np.ndarray) -> _Sparse:
        n = indptr.shape[0] - 1
        return _Sparse(n, n, data.shape[0], indptr.ctypes.data, indices.ctypes.data, None,
                       data.ctypes.data, None, 1, _INT_INDEX, _REAL, _DOUBLE, 1, 1)

    def _symbolic(self, data: np.ndarray, indices: np.ndarray, indptr: np.ndarray) -> int:
        if self.cache:  # LM factorises one pattern over and over: compare with the last
            last_ptr, last_ind, factor = next(reversed(self.cache.values()))
            if (last_ptr.shape == indptr.shape and last_ind.shape == indices.shape
                    and np.array_equal(last_ptr, indptr) and np.array_equal(last_ind, indices)):
                return factor  # no checksums: on parking-garage 0.56 ms of a 7.5 ms call
        key = (indptr.shape[0], indices.shape[0], zlib.crc32(indptr), zlib.crc32(indices))
        hit = self.cache.get(key)
        if hit is not None and np.array_equal(hit[0], indptr) and np.array_equal(hit[1], indices):
            self.cache.move_to_end(key)
            return hit[2]
        factor = self._analyze(data, indices, indptr)
        if hit is not None:
            self._free(hit[2])
        self.cache[key] = (indptr.copy(), indices.copy(), factor)
        while len(self.cache) > CACHE_SIZE:
            self._free(self.cache.popitem(last=False)[1][2])
        return factor

    def _analyze(self, data: np.ndarray, indices: np.ndarray, indptr: np.ndarray) -> int:
        """CHOLMOD's symbolic analysis; where its ordering needs more than
        :data:`METIS_FLOPS` flops and is not METIS, METIS's too, kept if it needs fewer
        than :data:`METIS_GAIN` times the flops (recorded in ``self.flops``)."""
        matrix = ctypes.byref(self._matrix(data, indices, indptr))
        factor = self.lib.cholmod_analyze(matrix, self.common)
        if not factor:
            raise MemoryError("cholmod_analyze failed")
        flops, ordering = self._chosen()
        if self.can_reorder and flops > METIS_FLOPS and ordering != _METIS:
            first = _METHODS + _ORDERING  # method[0]'s ordering, GIVEN by default
            default_first = struct.unpack_from("i", self.common, first)[0]
            struct.pack_into("i", self.common, _NMETHODS, 1)  # method[0] only, as METIS
            struct.pack_into("i", self.common, first, _METIS)
            try:
                other = self.lib.cholmod_analyze(matrix, self.common)
                other_flops = self._chosen()[0] if other else np.inf
            finally:
                struct.pack_into("i", self.common, _NMETHODS, 0)
                struct.pack_into("i", self.common, first, default_first)
            if other and other_flops < METIS_GAIN * flops:
                self._free(factor)
                factor, flops = other, other_flops
            elif other:
                self._free(other)
        self.flops[factor] = flops
        return factor

    def _chosen(self) -> tuple[float, int]:
        """(flops, ordering) of the method the last analysis selected."""
        at = _METHODS + struct.unpack_from("i", self.common, _SELECTED)[0] * _METHOD_SIZE
        return (struct.unpack_from("d", self.common, at + _FL)[0],
                struct.unpack_from("i", self.common, at + _ORDERING)[0])

    def _free(self, factor: int) -> None:
        self.flops.pop(factor, None)
        self.lib.cholmod_free_factor(ctypes.byref(_VOIDP(factor)), self.common)

    def solve(self, data: np.ndarray, indices: np.ndarray, indptr: np.ndarray,
              b: np.ndarray) -> np.ndarray:
        n = indptr.shape[0] - 1
        with self.lock:
            factor = self._symbolic(data, indices, indptr)
            self.lib.cholmod_factorize(ctypes.byref(self._matrix(data, indices, indptr)),
                                       factor, self.common)
            _, minor = struct.unpack("QQ", ctypes.string_at(factor, 16))  # L->n, L->minor
            if minor < n:  # not positive definite
                return np.full(b.shape, np.nan)
            k = 1 if b.ndim == 1 else b.shape[1]
            cols = np.asfortranarray(b.reshape(n, k))  # CHOLMOD's dense layout: column-major
            rhs = _Dense(n, k, n * k, n, cols.ctypes.data, None, _REAL, _DOUBLE)
            out = self.lib.cholmod_solve(_SOLVE_A, factor, ctypes.byref(rhs), self.common)
            if not out:
                return np.full(b.shape, np.nan)
            x = np.ctypeslib.as_array(ctypes.cast(out.contents.x, ctypes.POINTER(ctypes.c_double)),
                                      (k, n)).T.copy()
            self.lib.cholmod_free_dense(ctypes.byref(out), self.common)
            return x.reshape(b.shape)

    def clear(self) -> None:
        """Free the cached factorisations."""
        with self.lock:
            while self.cache:
                self._free(self.cache.popitem()[1][2])

    def close(self) -> None:
        self.clear()
        with self.lock:
            self.lib.cholmod_finish(self.common)


def _csr(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rows, cols = np.nonzero(a)
    indptr = np.searchsorted(rows, np.arange(a.shape[0] + 1)).astype(np.int32)
    return a[rows, cols].copy(), cols.astype(np.int32), indptr


def _self_test(lib: _Library) -> None:
    """SPD systems must solve to rounding and an indefinite one must be reported: a 3×3
    one and a 96×96 one with a dense 64×64 block (a supernode large enough to go through
    the BLAS kernels)."""
    a = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 1.0], [0.0, 1.0, 2.0]])
    rng = np.random.default_rng(0)
    g = rng.normal(size=(64, 64))
    big = np.diag(np.full(96, 4.0)) + np.diag(np.ones(95), 1) + np.diag(np.ones(95), -1)
    big[32:, 32:] += g @ g.T / 64
    for m in (a, big):
        b = np.linspace(1.0, 3.0, m.shape[0])
        x = lib.solve(*_csr(m), b)
        if not np.allclose(x, np.linalg.solve(m, b), rtol=1e-10, atol=0):
            raise OSError("CHOLMOD self-test: wrong solution (check the BLAS it uses: "
                          f"{_BLAS}; set JAXPOSE_BLAS=reference to use cholespy's own)")
    a[2, 2] = -2.0
    if not np.all(np.isnan(lib.solve(*_csr(a), np.ones(3)))):
        raise OSError("CHOLMOD self-test: an indefinite matrix was not reported")
    lib.clear()


def _preload_blas() -> str:
    """Load the optimised BLAS CHOLMOD should bind to (module docstring); returns what
    :func:`blas` reports. Warns (and keeps the reference BLAS) when ``JAXPOSE_BLAS`` names
    a library that cannot be loaded."""
    choice = os.environ.get("JAXPOSE_BLAS", "").strip()
    if choice == "reference":
        return "reference (JAXPOSE_BLAS=reference)"
    if "cholespy._cholespy_core" in sys.modules:
        return "reference (cholespy was imported before jaxpose loaded CHOLMOD)"
    if not choice and not sys.platform.startswith("linux"):
        return "cholespy's own"
    name = choice or ctypes.util.find_library("openblas")
    if name is None:
        return "reference (no system OpenBLAS found)"
    try:
        lib = ctypes.CDLL(name, mode=ctypes.RTLD_GLOBAL)
    except OSError as err:
        if choice:
            warnings.warn(f"JAXPOSE_BLAS={choice!r} could not be loaded ({err}); expected the "
                          "path or soname of an LP64 BLAS, or 'reference'. CHOLMOD keeps "
                          "cholespy's reference BLAS.", RuntimeWarning, stacklevel=4)
        return f"reference ({name!r} could not be loaded)"
    if "OPENBLAS_NUM_THREADS" not in os.environ and hasattr(lib, "openblas_set_num_threads"):
        lib.openblas_set_num_threads(1)  # see the module docstring
    return name


_LIB: _Library | None = None
_LOAD_ERROR: str | None = None
_LOADED = False
_BLAS = "not loaded"


def _load() -> _Library | None:
    global _LIB, _LOAD_ERROR, _LOADED, _BLAS
    if _LOADED:
        return _LIB
    _LOADED = True
    try:
        spec = importlib.util.find_spec("cholespy")  # located, not imported (see _preload_blas)
        if spec is None or not spec.submodule_search_locations:
            raise ImportError("cholespy is not installed")
        paths = glob.glob(os.path.join(spec.submodule_search_locations[0], "_cholespy_core*"))
        if not paths:
            raise OSError("cholespy's compiled core not found")
        _BLAS = _preload_blas()
        lib = _Library(paths[0])
        _self_test(lib)
        _LIB = lib
        atexit.register(lib.close)
    except (ImportError, OSError, AttributeError) as err:  # no usable CHOLMOD
        _LOAD_ERROR = f"{type(err).__name__}: {err}"
    return _LIB


def available() -> bool:
    """True when CHOLMOD could be loaded and passed its layout checks."""
    return _load() is not None


def blas() -> str:
    """The BLAS CHOLMOD's dense kernels use: a library path/soname, or ``reference ...``
    with the reason no optimised one was loaded (module docstring)."""
    _load()
    return _BLAS


def slow_blas() -> str | None:
    """When CHOLMOD has been loaded (a sparse solve ran) on the reference BLAS without the
    user asking for it (``JAXPOSE_BLAS=reference``): the reason, for a one-line notice
    (large supernodal factorisations are about 3x slower); else None."""
    if not _LOADED or _LIB is None:
        return None
    if _BLAS.startswith("reference") and "JAXPOSE_BLAS=reference" not in _BLAS:
        return _BLAS
    return None


def unavailable_reason() -> str | None:
    """Why :func:`available` is False (None when it is True)."""
    _load()
    return _LOAD_ERROR


def solve(data: Any, indices: Any, indptr: Any, b: Any) -> np.ndarray:
    """Solve A x = b for SPD A in symmetric CSR (float64 result; NaN if A is not SPD);
    ``b`` is (n,) or (n, k) (k right-hand sides, one factorisation).

    The symbolic factorisation of the pattern (``indices``, ``indptr``) is cached."""
    lib = _load()
    if lib is None:
        raise RuntimeError(f"CHOLMOD is not available ({_LOAD_ERROR})")
    return lib.solve(np.ascontiguousarray(data, np.float64),
                     np.ascontiguousarray(indices, np.int32),
                     np.ascontiguousarray(indptr, np.int32),
                     np.ascontiguousarray(b, np.float64))
