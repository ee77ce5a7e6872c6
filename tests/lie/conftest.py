"""Shared set-up, hypothesis strategies and independent references for the Lie-group tests.

* float64 is enabled for the whole session; every test passes its dtype explicitly so the
  float32 paths are exercised too.
* Strategies: ``GROUPS`` / ``ALGEBRAS``, ``batch_shapes()``, ``dtypes()``, ``tangents(...)``
  (controllable rotation-angle range), ``group_data(...)``, ``cases(...)`` (a drawn batch
  shape + dtype + seeded generator bundled as a :class:`Case`).
* References built without the code under test: ``ref_matrix`` (storage → matrix, via
  scipy's quaternion conversion), ``ref_hat`` / ``ref_vee``, ``ref_exp_matrix``
  (scipy.linalg.expm), ``ref_log`` (scipy.linalg.logm), ``rot_x/rot_y/rot_z``.
* ``J``: jitted wrappers around the public methods, compiled with :data:`FAST_COMPILE`. XLA
  compilation dominates the run time of this suite, so the property tests call these shared
  wrappers (one compilation per op, group, batch shape and dtype for the whole session)
  instead of compiling their own kernels or running eagerly (eager compiles every primitive
  separately, about twice the cost); ``test_transforms.py`` checks that jit and eager agree.

Other test modules import the helpers with ``from .conftest import ...`` (``tests/lie`` is a
package).
"""

from __future__ import annotations

import dataclasses
import os
from types import SimpleNamespace
from typing import Any

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from jaxpose.lie import (  # noqa: E402
    SE2,
    SE3,
    SO2,
    SO3,
    LieAlgebra,
    LieGroup,
    RxSO3,
    Sim3,
    rxso3,
    se2,
    se3,
    sim3,
    so2,
    so3,
)

# ------------------------------------------------------------------------------------
# hypothesis profiles: deterministic in CI, HYPOTHESIS_PROFILE=dev for a wider search
# ------------------------------------------------------------------------------------
_COMMON = dict(
    deadline=None,
    suppress_health_check=[
        HealthCheck.too_slow,
        HealthCheck.function_scoped_fixture,
        HealthCheck.differing_executors,
        HealthCheck.data_too_large,
    ],
    print_blob=True,
)
settings.register_profile("jaxpose", max_examples=6, derandomize=True, database=None, **_COMMON)
settings.register_profile("dev", max_examples=60, **_COMMON)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "jaxpose"))

# ------------------------------------------------------------------------------------
# groups, layouts and tolerances
# ------------------------------------------------------------------------------------
GROUPS: tuple[type[LieGroup], ...] = (SO3, SE3, Sim3, RxSO3, SO2, SE2)
ALGEBRAS: tuple[type[LieAlgebra], ...] = (so3, se3, sim3, rxso3, so2, se2)
GROUPS_3D = (SO3, SE3, Sim3, RxSO3)
BATCH_SHAPES: tuple[tuple[int, ...], ...] = ((), (1,), (3, 1, 2))
DTYPES = (np.float32, np.float64)

# where the parts of a tangent vector live (algebra layouts, translation first)
ROT_SLICE = {
    SO3: slice(0, 3),
    SE3: slice(3, 6),
    Sim3: slice(3, 6),
    RxSO3: slice(0, 3),
    SO2: slice(0, 1),
    SE2: slice(2, 3),
}
TRANS_SLICE = {SE3: slice(0, 3), Sim3: slice(0, 3), SE2: slice(0, 2)}
SCALE_INDEX = {Sim3: 6, RxSO3: 3}
# where the parts of the stored data live (group layouts)
QUAT_SLICE = {SO3: slice(0, 4), SE3: slice(3, 7), Sim3: slice(3, 7), RxSO3: slice(0, 4)}
COSSIN_SLICE = {SO2: slice(0, 2), SE2: slice(2, 4)}
DATA_TRANS_SLICE = {SE3: slice(0, 3), Sim3: slice(0, 3), SE2: slice(0, 2)}
DATA_SCALE_INDEX = {Sim3: 7, RxSO3: 4}


def gid(cls: Any) -> str:
    """pytest id for a group / algebra class or a dtype."""
    return getattr(cls, "__name__", str(cls))


def tol(dtype: Any, f64: float = 1e-10, f32: float = 1e-4) -> float:
    return f64 if np.dtype(dtype) == np.float64 else f32


def assert_close(
    actual: Any, expected: Any, dtype: Any, f64: float = 1e-10, f32: float = 1e-4, err_msg: str = ""
) -> None:
    """|actual − expected| ≤ t·(1 + |expected|) elementwise, t chosen by dtype."""
    t = tol(dtype, f64, f32)
    a = np.asarray(actual, np.float64)
    e = np.asarray(expected, np.float64)
    assert a.shape == e.shape, f"shape {a.shape} != {e.shape} {err_msg}"
    np.testing.assert_allclose(a, e, rtol=t, atol=t, err_msg=err_msg)


def assert_dtype(x: Any, dtype: Any) -> None:
    d = x.dtype if hasattr(x, "dtype") else np.asarray(x).dtype
    assert np.dtype(d) == np.dtype(dtype), f"dtype {d}, expected {np.dtype(dtype)}"


# ------------------------------------------------------------------------------------
# random data (numpy, independent of jaxpose)
# ------------------------------------------------------------------------------------
def _unit_vectors(rng: np.random.Generator, shape: tuple[int, ...], n: int) -> np.ndarray:
    v = rng.normal(size=(*shape, n))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_tangent(
    rng: np.random.Generator,
    cls: type[LieGroup],
    shape: tuple[int, ...],
    min_angle: float = 0.0,
    max_angle: float = 3.0,
    trans_scale: float = 1.0,
    max_log_scale: float = 1.0,
) -> np.ndarray:
    """float64 tangent vectors for ``cls`` whose rotation angle is uniform in
    [min_angle, max_angle] (random axis / sign), translation ~ N(0, trans_scale²) and
    log-scale ~ U(−max_log_scale, max_log_scale)."""
    d = cls.tangent_dim
    a = np.zeros((*shape, d))
    angle = rng.uniform(min_angle, max_angle, size=shape)
    rs = ROT_SLICE[cls]
    if rs.stop - rs.start == 3:
        a[..., rs] = _unit_vectors(rng, shape, 3) * angle[..., None]
    else:
        a[..., rs] = (rng.choice([-1.0, 1.0], size=shape) * angle)[..., None]
    if cls in TRANS_SLICE:
        ts = TRANS_SLICE[cls]
        a[..., ts] = trans_scale * rng.normal(size=(*shape, ts.stop - ts.start))
    if cls in SCALE_INDEX:
        a[..., SCALE_INDEX[cls]] = rng.uniform(-max_log_scale, max_log_scale, size=shape)
    return a


def random_group_data(
    rng: np.random.Generator,
    cls: type[LieGroup],
    shape: tuple[int, ...],
    trans_scale: float = 1.0,
    max_log_scale: float = 1.0,
) -> np.ndarray:
    """float64 storage arrays of valid elements, built directly in the storage layout
    (uniform rotations, either quaternion sign)."""
    parts = []
    if cls in (SE3, Sim3):
        parts.append(trans_scale * rng.normal(size=(*shape, 3)))
    if cls is SE2:
        parts.append(trans_scale * rng.normal(size=(*shape, 2)))
    if cls in QUAT_SLICE:
        parts.append(_unit_vectors(rng, shape, 4))
    else:
        th = rng.uniform(-np.pi, np.pi, size=shape)
        parts.append(np.stack([np.cos(th), np.sin(th)], -1))
    if cls in SCALE_INDEX:
        parts.append(np.exp(rng.uniform(-max_log_scale, max_log_scale, size=(*shape, 1))))
    return np.concatenate(parts, -1)


@dataclasses.dataclass
class Case:
    """A drawn test case: group, batch shape, dtype and a seeded numpy generator."""

    cls: type[LieGroup]
    shape: tuple[int, ...]
    dtype: Any
    rng: np.random.Generator

    @property
    def alg(self) -> type[LieAlgebra]:
        return self.cls.algebra

    def cast(self, x: Any) -> np.ndarray:
        return np.asarray(x, self.dtype)

    def tangent(self, shape: tuple[int, ...] | None = None, **kw: Any) -> np.ndarray:
        s = self.shape if shape is None else shape
        return self.cast(random_tangent(self.rng, self.cls, s, **kw))

    def element(self, shape: tuple[int, ...] | None = None, **kw: Any) -> LieGroup:
        s = self.shape if shape is None else shape
        return self.cls(self.cast(random_group_data(self.rng, self.cls, s, **kw)))

    def points(self, shape: tuple[int, ...] | None = None, homogeneous: bool = False) -> np.ndarray:
        s = self.shape if shape is None else shape
        p = self.rng.normal(size=(*s, self.cls.point_dim + int(homogeneous)))
        return self.cast(p)


def batch_shapes() -> st.SearchStrategy[tuple[int, ...]]:
    return st.sampled_from(BATCH_SHAPES)


def dtypes() -> st.SearchStrategy[Any]:
    return st.sampled_from(DTYPES)


def seeds() -> st.SearchStrategy[int]:
    return st.integers(0, 2**32 - 1)


@st.composite
def cases(
    draw: Any,
    cls: type[LieGroup],
    dtype: Any = None,
    shapes: tuple[tuple[int, ...], ...] = BATCH_SHAPES,
) -> Case:
    """A :class:`Case` for ``cls``; ``dtype`` drawn from float32/float64 unless given."""
    shape = draw(st.sampled_from(shapes))
    dt = draw(dtypes()) if dtype is None else dtype
    return Case(cls, shape, dt, np.random.default_rng(draw(seeds())))


@st.composite
def tangents(
    draw: Any,
    cls: type[LieGroup],
    shape: tuple[int, ...] = (),
    dtype: Any = np.float64,
    min_angle: float = 0.0,
    max_angle: float = 3.0,
    trans_scale: float = 1.0,
    max_log_scale: float = 1.0,
) -> np.ndarray:
    """Tangent vectors (numpy, ``dtype``) with the rotation angle in [min_angle, max_angle]."""
    rng = np.random.default_rng(draw(seeds()))
    return np.asarray(
        random_tangent(rng, cls, shape, min_angle, max_angle, trans_scale, max_log_scale), dtype
    )


@st.composite
def group_data(
    draw: Any, cls: type[LieGroup], shape: tuple[int, ...] = (), dtype: Any = np.float64
) -> np.ndarray:
    """Storage arrays of valid group elements (numpy, ``dtype``)."""
    rng = np.random.default_rng(draw(seeds()))
    return np.asarray(random_group_data(rng, cls, shape), dtype)


# ------------------------------------------------------------------------------------
# independent references (numpy / scipy, float64)
# ------------------------------------------------------------------------------------
def _quat_to_rot(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, np.float64)
    flat = q.reshape(-1, 4)
    r = Rotation.from_quat(flat).as_matrix()  # scalar-last [x, y, z, w], as stored
    return r.reshape(*q.shape[:-1], 3, 3)


def _rot2(cs: np.ndarray) -> np.ndarray:
    c, s = cs[..., 0], cs[..., 1]
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _affine(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    n = r.shape[-1]
    m = np.zeros((*r.shape[:-2], n + 1, n + 1))
    m[..., :n, :n] = r
    m[..., :n, n] = t
    m[..., n, n] = 1.0
    return m


def ref_matrix(cls: type[LieGroup], data: Any) -> np.ndarray:
    """Matrix of a stored element, from the documented storage layout (float64)."""
    x = np.asarray(data, np.float64)
    if cls is SO3:
        return _quat_to_rot(x)
    if cls is SE3:
        return _affine(_quat_to_rot(x[..., 3:7]), x[..., :3])
    if cls is Sim3:
        return _affine(x[..., 7, None, None] * _quat_to_rot(x[..., 3:7]), x[..., :3])
    if cls is RxSO3:
        return x[..., 4, None, None] * _quat_to_rot(x[..., :4])
    if cls is SO2:
        return _rot2(x)
    if cls is SE2:
        return _affine(_rot2(x[..., 2:4]), x[..., :2])
    raise TypeError(cls)


def _skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = np.zeros_like(x)
    return np.stack(
        [np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], -2
    )


def ref_hat(cls: type[LieGroup], a: Any) -> np.ndarray:
    """Matrix form of a tangent vector in the algebra layout of ``cls`` (float64)."""
    a = np.asarray(a, np.float64)
    if cls is SO3:
        return _skew(a)
    if cls is RxSO3:
        return _skew(a[..., :3]) + a[..., 3, None, None] * np.eye(3)
    if cls is SO2:
        o = np.zeros_like(a[..., 0])
        return np.stack([np.stack([o, -a[..., 0]], -1), np.stack([a[..., 0], o], -1)], -2)
    if cls in (SE3, Sim3):
        block = _skew(a[..., 3:6])
        if cls is Sim3:
            block = block + a[..., 6, None, None] * np.eye(3)
        m = np.zeros((*a.shape[:-1], 4, 4))
        m[..., :3, :3] = block
        m[..., :3, 3] = a[..., :3]
        return m
    if cls is SE2:
        m = np.zeros((*a.shape[:-1], 3, 3))
        m[..., 0, 1] = -a[..., 2]
        m[..., 1, 0] = a[..., 2]
        m[..., :2, 2] = a[..., :2]
        return m
    raise TypeError(cls)


def ref_vee(cls: type[LieGroup], m: Any) -> np.ndarray:
    """Inverse of :func:`ref_hat`."""
    m = np.asarray(m, np.float64)

    def so3v(b: np.ndarray) -> np.ndarray:
        return 0.5 * np.stack(
            [b[..., 2, 1] - b[..., 1, 2], b[..., 0, 2] - b[..., 2, 0], b[..., 1, 0] - b[..., 0, 1]],
            -1,
        )

    if cls is SO3:
        return so3v(m)
    if cls is RxSO3:
        return np.concatenate([so3v(m), np.trace(m, axis1=-2, axis2=-1)[..., None] / 3.0], -1)
    if cls is SO2:
        return 0.5 * (m[..., 1, 0] - m[..., 0, 1])[..., None]
    if cls is SE3:
        return np.concatenate([m[..., :3, 3], so3v(m[..., :3, :3])], -1)
    if cls is Sim3:
        sig = np.trace(m[..., :3, :3], axis1=-2, axis2=-1)[..., None] / 3.0
        return np.concatenate([m[..., :3, 3], so3v(m[..., :3, :3]), sig], -1)
    if cls is SE2:
        return np.concatenate([m[..., :2, 2], (0.5 * (m[..., 1, 0] - m[..., 0, 1]))[..., None]], -1)
    raise TypeError(cls)


def _map_matrices(fn: Any, m: np.ndarray) -> np.ndarray:
    flat = m.reshape(-1, *m.shape[-2:])
    return np.stack([fn(x) for x in flat]).reshape(m.shape)


def ref_exp_matrix(cls: type[LieGroup], a: Any) -> np.ndarray:
    """expm(hat(a)) with scipy (float64)."""
    return _map_matrices(scipy.linalg.expm, ref_hat(cls, a))


def ref_log(cls: type[LieGroup], data: Any) -> np.ndarray:
    """Principal matrix logarithm (scipy.linalg.logm) of the element, as a tangent vector."""
    logs = _map_matrices(lambda x: np.real(scipy.linalg.logm(x)), ref_matrix(cls, data))
    return ref_vee(cls, logs)


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def assert_same_element(
    x: LieGroup, y: Any, dtype: Any, f64: float = 1e-10, f32: float = 1e-4, err_msg: str = ""
) -> None:
    """Same group element (compared as matrices, so q and −q agree). ``y`` may be an element
    or a reference matrix."""
    assert isinstance(x, LieGroup)
    m_y = ref_matrix(type(x), y.data) if isinstance(y, LieGroup) else np.asarray(y)
    assert_close(ref_matrix(type(x), x.data), m_y, dtype, f64, f32, err_msg)


def central_diff(f: Any, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Central finite-difference Jacobian of a vectorised f: (n,) → (m,), shape (m, n).

    ``f`` receives a (2n, n) stack of perturbed inputs and returns (2n, m)."""
    x = np.asarray(x, np.float64)
    n = x.size
    e = np.eye(n) * eps
    pts = np.concatenate([x[None] + e, x[None] - e], 0)
    out = np.asarray(f(pts), np.float64)
    return ((out[:n] - out[n:]) / (2 * eps)).T


# ------------------------------------------------------------------------------------
# jitted wrappers around the public methods (shared compilation cache)
# ------------------------------------------------------------------------------------
# XLA's default CPU pipeline makes compilation dominate this suite's run time (nested
# derivatives above all); these options cut it three- to fivefold and change results only by
# rounding (no fast-math). Scoped to the tests' own jits (a global XLA_FLAGS would leak into
# the whole session). CPU options only: other backends reject them, and compile as they ship.
FAST_COMPILE = {
    "xla_backend_optimization_level": 0,
    "xla_cpu_use_fusion_emitters": False,
    "xla_llvm_disable_expensive_passes": True,
} if jax.default_backend() == "cpu" else {}


def fast_jit(fun: Any = None, **kw: Any) -> Any:
    """``jax.jit`` with :data:`FAST_COMPILE` (usable as ``@fast_jit`` or
    ``@fast_jit(static_argnums=...)``)."""
    if fun is None:
        return lambda f: jax.jit(f, compiler_options=FAST_COMPILE, **kw)
    return jax.jit(fun, compiler_options=FAST_COMPILE, **kw)


J = SimpleNamespace(
    exp=fast_jit(lambda a: a.exp()),  # algebra element → group
    log=fast_jit(lambda x: x.log()),
    inv=fast_jit(lambda x: x.inv()),
    compose=fast_jit(lambda x, y: x @ y),
    act=fast_jit(lambda x, p: x @ p),
    matrix=fast_jit(lambda x: x.matrix()),
    adj=fast_jit(lambda x, a: x.adj(a)),
    adjT=fast_jit(lambda x, a: x.adjT(a)),
    adj_matrix=fast_jit(lambda x: x.adj_matrix()),
    jinvp=fast_jit(lambda x, a: x.jinvp(a)),
    jr=fast_jit(lambda a: a.jr()),
    jl=fast_jit(lambda a: a.jl()),
    jr_inv=fast_jit(lambda a: a.jr_inv()),
    jl_inv=fast_jit(lambda a: a.jl_inv()),
    hat=fast_jit(lambda a: a.hat()),
    from_matrix=fast_jit(
        lambda m, cls, check=True: cls.from_matrix(m, check=check), static_argnums=(1, 2)
    ),
    normalize=fast_jit(lambda x: x.normalize()),
    interpolate=fast_jit(lambda x, y, t: x.interpolate(y, t)),
    cumprod=fast_jit(lambda x, axis, left: x.cumprod(axis, left), static_argnums=(1, 2)),
    retract=fast_jit(lambda x, d: x.retract(d)),
    rminus=fast_jit(lambda x, y: x.rminus(y)),
    euler=fast_jit(lambda x: x.euler()),
    from_euler=fast_jit(lambda e: SO3.from_euler(e)),
)


def tangent_array(a: Any) -> np.ndarray:
    """The data of an algebra element (or an array) as float64 numpy."""
    return np.asarray(a.data if isinstance(a, LieAlgebra) else a, np.float64)


__all__ = [
    "ALGEBRAS",
    "BATCH_SHAPES",
    "COSSIN_SLICE",
    "DATA_SCALE_INDEX",
    "DATA_TRANS_SLICE",
    "DTYPES",
    "FAST_COMPILE",
    "GROUPS",
    "GROUPS_3D",
    "J",
    "QUAT_SLICE",
    "ROT_SLICE",
    "SCALE_INDEX",
    "TRANS_SLICE",
    "Case",
    "assert_close",
    "assert_dtype",
    "assert_same_element",
    "batch_shapes",
    "cases",
    "central_diff",
    "dtypes",
    "fast_jit",
    "gid",
    "group_data",
    "random_group_data",
    "random_tangent",
    "ref_exp_matrix",
    "ref_hat",
    "ref_log",
    "ref_matrix",
    "ref_vee",
    "rot_x",
    "rot_y",
    "rot_z",
    "seeds",
    "tangent_array",
    "tangents",
    "tol",
]
