"""Shared base classes for Lie groups and Lie algebras.

Every group or algebra element is an :class:`equinox.Module` (hence a pytree) with
a single array field ``data`` of shape ``(*batch, dim)``. Leading batch axes
broadcast like numpy between operands. Concrete groups implement a handful of raw
array functions (``_exp``, ``_log``, ``_compose``, ...); everything else — the
operators, interpolation, cumulative products, Jacobians of every algebra — is
written once here in terms of them.

Conventions (shared with PyPose, see ``docs/conventions.md``):

* right Jacobian ``Jr(a)``: ``Exp(a + δ) ≈ Exp(a) · Exp(Jr(a) δ)``;
* left Jacobian ``Jl(a) = Jr(−a)``: ``Exp(a + δ) ≈ Exp(Jl(a) δ) · Exp(a)``;
* adjoint ``Adj(X)``: ``X · Exp(a) = Exp(Adj(X) a) · X``;
* retraction (used by the optimizers): ``X ⊕ δ = X · Exp(δ)`` (right perturbation).
"""

from __future__ import annotations

import operator
from collections.abc import Iterator, Sequence
from typing import Any, ClassVar, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array as _as_float_array
from .._precision import FULL

Array = jax.Array
G = TypeVar("G", bound="LieGroup")
E = TypeVar("E", bound="_Element")
A = TypeVar("A", bound="LieAlgebra")


# ----------------------------------------------------------------------------------
# Validation helpers (trace-time: shapes and types only)
# ----------------------------------------------------------------------------------
def as_float_array(x: Any, argname: str) -> Array:
    """Convert ``x`` to a floating JAX array, with a clear error for non-arrays (a group
    or algebra element is refused: its ``.data`` is the array)."""
    if isinstance(x, (LieGroup, LieAlgebra)):
        raise TypeError(
            f"{argname}: expected an array, got a {type(x).__name__} element; "
            f"use its `.data` if you meant the stored array"
        )
    return _as_float_array(x, argname, "an array-like of numbers")


def check_last_dim(arr: Array, dims: int | tuple[int, ...], argname: str, layout: str) -> None:
    allowed = (dims,) if isinstance(dims, int) else dims
    if arr.ndim == 0 or arr.shape[-1] not in allowed:
        want = " or ".join(str(d) for d in allowed)
        raise ValueError(
            f"{argname}: expected an array of shape (..., {want}) with layout {layout}, "
            f"got shape {tuple(arr.shape)}"
        )


def broadcast_batch(*shapes: tuple[int, ...], what: str) -> tuple[int, ...]:
    """Broadcast batch shapes or raise a ValueError that names the operation."""
    try:
        return tuple(np.broadcast_shapes(*shapes))
    except ValueError as err:
        raise ValueError(
            f"{what}: batch shapes {', '.join(str(tuple(s)) for s in shapes)} do not broadcast"
        ) from err


def as_batch_shape(shape: Any, argname: str) -> tuple[int, ...]:
    """A batch shape from an int or a sequence of ints: ``4`` and ``(4,)`` are the same."""
    if isinstance(shape, (int, np.integer)) and not isinstance(shape, bool):
        shape = (shape,)
    try:
        out = tuple(operator.index(n) for n in shape)
    except TypeError as err:
        raise TypeError(
            f"{argname}: expected an int or a sequence of ints, got {shape!r}"
        ) from err
    if any(n < 0 for n in out):
        raise ValueError(f"{argname}: negative dimension in batch shape {out}")
    return out


def _default_tol(dtype: Any) -> float:
    """Default run-time check tolerance: 1e-5 for float32 (and narrower), 1e-9 for float64."""
    return 1e-9 if jnp.dtype(dtype) == jnp.float64 else 1e-5


def max_abs(parts: Sequence[Array]) -> Array:
    """max |pᵢ| over a few (…,) arrays: the scale that makes norms overflow- and underflow-safe."""
    out = jnp.abs(parts[0])
    for p in parts[1:]:
        out = jnp.maximum(out, jnp.abs(p))
    return out


def scaled_norm(v: Array) -> Array:
    """Euclidean norm over the last (short) axis (…, k) → (…,) without overflow or
    underflow: ``m·|v/m|`` with m = max |vᵢ| (0 for v = 0)."""
    parts = [v[..., i] for i in range(v.shape[-1])]
    m = max_abs(parts)
    inv = 1.0 / jnp.where(m > 0, m, 1.0)
    s = parts[0] * inv
    acc = s * s
    for p in parts[1:]:
        s = p * inv
        acc = acc + s * s
    return m * jnp.sqrt(acc)


class InvalidValueError(ValueError, RuntimeError):
    """A run-time value check failed eagerly (``check=True`` options). Under ``jit`` the
    same message arrives through :func:`equinox.error_if` as a ``RuntimeError``
    (``equinox.EquinoxRuntimeError`` under ``eqx.filter_jit``), so ``except RuntimeError``
    catches both."""


def runtime_check(x: Any, bad: Array, msg: str) -> Any:
    """Raise ``msg`` if ``bad`` (a bool array) is true: a one-line
    :class:`InvalidValueError` when the value is known in Python (eager), otherwise
    :func:`equinox.error_if` (under ``jit`` / ``vmap``). Returns ``x``."""
    if isinstance(bad, jax.core.Tracer):
        return eqx.error_if(x, bad, msg)
    if bool(bad):
        raise InvalidValueError(msg)
    return x


def _check_same_type(x: Any, y: Any, what: str) -> None:
    if type(x) is not type(y):
        raise TypeError(
            f"{what}: expected two {type(x).__name__} elements, got "
            f"{type(x).__name__} and {type(y).__name__}"
        )


def parts(a: Array, axis: int = -1) -> list[Array]:
    """The components of ``a`` along ``axis`` as arrays without that axis, cut by one
    ``split`` (whose transpose is one ``concatenate``). Indexing (``a[..., 0]``) transposes
    to a ``pad`` per component, which XLA:CPU fuses apart, each fusion recomputing the
    components' shared producers: the gradient of a solve over SE(3) residuals held three
    copies of ~550-instruction fusions that way (its XLA compile 13 % longer), and
    ``jnp.take`` is a gather that transposes to a scatter-add."""
    return [jnp.squeeze(c, axis) for c in jnp.split(a, a.shape[axis], axis)]


def skew(v: Array) -> Array:
    """[v]× of shape (..., 3, 3) from v of shape (..., 3): [v]× p = v × p."""
    x, y, z = parts(v)
    o = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2
    )


def vee(m: Array) -> Array:
    """Inverse of :func:`skew`: (..., 3, 3) → (..., 3)."""
    return jnp.stack([m[..., 2, 1], m[..., 0, 2], m[..., 1, 0]], -1)


def matvec(m: Array, v: Array) -> Array:
    """Batched matrix-vector product (..., n, m) @ (..., m) → (..., n)."""
    return jnp.einsum("...ij,...j->...i", m, v, precision=FULL)


def small_matmul(a: Array, b: Array) -> Array:
    """Batched product of small matrices (..., n, k) @ (..., k, p) → (..., n, p), written
    as a sum of k outer products: XLA fuses it into one elementwise loop, where XLA:CPU's
    batched dot runs per matrix (measured: 6275 products of 6×6 matrices in 0.19 ms
    against 1.7 ms, 12-column Gram matrices JᵀJ 0.33 ms against 2.4 ms). Inner sizes
    k > 16 use ``jnp.matmul`` (the unrolled sum would grow the program), at full float32
    precision on every backend (:mod:`jaxpose._precision`)."""
    k = a.shape[-1]
    if k > 16:
        return jnp.matmul(a, b, precision=FULL)
    return sum(a[..., :, i, None] * b[..., None, i, :] for i in range(k))


def small_matvec(a: Array, v: Array) -> Array:
    """Batched (..., n, k) @ (..., k) → (..., n) as :func:`small_matmul` (one fused loop
    where XLA:CPU's batched dot runs per matrix: eight per LM iteration of the graph path
    were a sixth of a tiny graph's solve). Not always faster: XLA recomputes a fused
    result in each of its consumers (PCG's block-Jacobi preconditioner, whose output
    several CG updates read, ran 5 % slower on parking-garage with it)."""
    return small_matmul(a, v[..., None])[..., 0]


# Gauss–Legendre nodes/weights on [0, 1], used for Jl(ξ) = ∫₀¹ Ad(Exp(uξ)) du on groups
# without a closed form (Sim3). Exact to float64 precision for |ξ| up to ~10.
_GL_N = 16
_gl_x, _gl_w = np.polynomial.legendre.leggauss(_GL_N)
GL_NODES = 0.5 * (_gl_x + 1.0)
GL_WEIGHTS = 0.5 * _gl_w


# ----------------------------------------------------------------------------------
# Shared element protocol: indexing, iteration, printing, equality
# ----------------------------------------------------------------------------------
class _Element(eqx.Module):
    """What group and algebra elements share: one array ``data`` (…, k) whose last axis is
    the element's own (storage or tangent) axis and whose leading axes are the batch."""

    data: Array

    @property
    def shape(self) -> tuple[int, ...]:
        """Batch shape (the data shape without the last axis)."""
        return tuple(self.data.shape[:-1])

    @property
    def dtype(self) -> Any:
        """Floating dtype of ``data``."""
        return self.data.dtype

    def __getitem__(self: E, idx: Any) -> E:
        return type(self)(self.data[_batch_index(idx, self)])

    def __len__(self) -> int:
        if not self.shape:
            raise TypeError(f"len() of an unbatched {type(self).__name__} (batch shape ())")
        return self.shape[0]

    def __iter__(self: E) -> Iterator[E]:
        if not self.shape:
            raise TypeError(
                f"iteration over an unbatched {type(self).__name__} (batch shape ()), "
                f"like a 0-d array"
            )
        return (self[i] for i in range(self.shape[0]))

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        """``np.asarray(X)`` is the stored ``data`` (…, k), as for a PyPose LieTensor."""
        return np.asarray(self.data, dtype=dtype)

    # numpy ufuncs and operators (``array == X``, ``np.add(X, 1)``) do not treat an element
    # as its data array: they defer to the element's own operators or raise TypeError
    __array_ufunc__ = None

    def __repr__(self) -> str:
        name = type(self).__name__
        data = self.data
        if isinstance(data, (np.ndarray, jax.Array)) and not isinstance(data, jax.core.Tracer):
            try:
                arr = np.asarray(data)
            except Exception:  # noqa: BLE001 - printing must never fail
                return super().__repr__()
            body = np.array2string(arr, separator=", ", prefix=f"{name}(")
            return f"{name}({body}, dtype={arr.dtype})"
        return super().__repr__()

    __str__ = __repr__

    def __eq__(self, other: Any) -> Any:
        """Elementwise equality of the stored data: a bool array of the broadcast batch
        shape (q and −q are different data for the same rotation; compare with
        ``rminus`` for geometric closeness)."""
        if type(other) is not type(self):
            return NotImplemented
        broadcast_batch(self.shape, other.shape, what=f"{type(self).__name__} ==")
        return jnp.all(self.data == other.data, axis=-1)

    def __ne__(self, other: Any) -> Any:
        eq = self.__eq__(other)
        return eq if eq is NotImplemented else ~eq

    __hash__ = eqx.Module.__hash__


# ----------------------------------------------------------------------------------
# Lie algebra base
# ----------------------------------------------------------------------------------
class LieAlgebra(_Element):
    """Element of a Lie algebra in vector form: ``data`` has shape (*batch, tangent_dim).

    ``check=True`` verifies at run time (``eqx.error_if``, also under ``jit``) that every
    entry is finite."""

    tangent_dim: ClassVar[int]
    layout: ClassVar[str]
    group: ClassVar[type[LieGroup]]

    def __init__(self, data: Any, check: bool = False):
        name = f"{type(self).__name__}(data)"
        arr = as_float_array(data, name)
        check_last_dim(arr, self.tangent_dim, name, self.layout)
        if check:
            arr = runtime_check(
                arr, ~jnp.all(jnp.isfinite(arr)),
                f"{type(self).__name__}(data, check=True): data has non-finite entries",
            )
        self.data = arr

    # -- shape helpers -------------------------------------------------------------
    def reshape(self: A, *shape: int) -> A:
        """Reshape the batch axes (the tangent axis is kept): ``a.reshape(2, 3)``."""
        shape = _shape_args(shape)
        return type(self)(self.data.reshape(*shape, self.tangent_dim))

    # -- arithmetic (vector space) -------------------------------------------------
    def __add__(self: A, other: A) -> A:
        _check_same_type(self, other, "algebra addition")
        broadcast_batch(self.shape, other.shape, what=f"{type(self).__name__} addition")
        return type(self)(self.data + other.data)

    def __sub__(self: A, other: A) -> A:
        _check_same_type(self, other, "algebra subtraction")
        broadcast_batch(self.shape, other.shape, what=f"{type(self).__name__} subtraction")
        return type(self)(self.data - other.data)

    def __neg__(self: A) -> A:
        return type(self)(-self.data)

    def __mul__(self: A, scalar: Any) -> A:
        s = jnp.asarray(scalar)
        return type(self)(self.data * s[..., None])

    __rmul__ = __mul__

    # -- Lie operations ------------------------------------------------------------
    def exp(self) -> LieGroup:
        """Exponential map to the group."""
        return self.group(self.group._exp(self.data))

    def Exp(self) -> LieGroup:  # noqa: N802 - PyPose spelling
        """PyPose spelling of :meth:`exp`."""
        return self.exp()

    def hat(self) -> Array:
        """Matrix form of the algebra element (…, n, n)."""
        return self.group._hat(self.data)

    def matrix(self) -> Array:
        """Matrix of ``Exp(self)`` (PyPose's ``LieTensor.matrix()`` on algebras)."""
        return self.exp().matrix()

    def jr(self) -> Array:
        """Right Jacobian (…, d, d): Exp(a + δ) ≈ Exp(a)·Exp(Jr δ)."""
        return self.group._jl(-self.data)

    def jl(self) -> Array:
        """Left Jacobian (…, d, d): Exp(a + δ) ≈ Exp(Jl δ)·Exp(a)."""
        return self.group._jl(self.data)

    def jr_inv(self) -> Array:
        """Inverse right Jacobian (…, d, d)."""
        return self.group._jl_inv(-self.data)

    def jl_inv(self) -> Array:
        """Inverse left Jacobian (…, d, d)."""
        return self.group._jl_inv(self.data)

    def Jr(self) -> Array:  # noqa: N802 - PyPose spelling
        """PyPose spelling of :meth:`jr`."""
        return self.jr()


# ----------------------------------------------------------------------------------
# Lie group base
# ----------------------------------------------------------------------------------
class LieGroup(_Element):
    """Element of a matrix Lie group: ``data`` has shape (*batch, storage_dim).

    ``G(data)`` checks the shape only; ``G(data, check=True)`` also verifies at run time
    (``eqx.error_if``, eager and under ``jit``) that every entry is finite, the quaternion
    or ``[cos θ, sin θ]`` has unit norm within ``tol`` (default 1e-9 float64, 1e-5
    float32) and the scale of Sim3 / RxSO3 is positive.

    Subclasses set the class constants and implement the raw array functions
    ``_exp, _log, _compose, _inv, _act, _matrix, _from_matrix, _adj_matrix, _jl,
    _jl_inv, _hat, _identity_data`` (all on plain arrays with broadcasting).
    """

    storage_dim: ClassVar[int]
    tangent_dim: ClassVar[int]
    matrix_dim: ClassVar[int]
    point_dim: ClassVar[int]  # 3 for 3D groups, 2 for planar ones
    layout: ClassVar[str]
    algebra: ClassVar[type[LieAlgebra]]
    # where the unit quaternion / unit complex number and the scale sit in ``data``
    unit_slice: ClassVar[tuple[int, int]]
    scale_index: ClassVar[int | None] = None

    def __init__(self, data: Any, check: bool = False, tol: float | None = None):
        name = f"{type(self).__name__}(data)"
        arr = as_float_array(data, name)
        check_last_dim(arr, self.storage_dim, name, self.layout)
        self.data = self._validate(arr, tol) if check else arr

    def _validate(self, arr: Array, tol: float | None) -> Array:
        """Run-time checks of ``check=True`` (``eqx.error_if``: eager and under ``jit``)."""
        name = f"{type(self).__name__}(data, check=True)"
        if arr.size == 0:
            return arr
        tol_ = _default_tol(arr.dtype) if tol is None else tol
        a, b = self.unit_slice
        what = "quaternion [qx, qy, qz, qw]" if b - a == 4 else "[cos θ, sin θ]"
        norm = scaled_norm(arr[..., a:b])
        arr = runtime_check(arr, ~jnp.all(jnp.isfinite(arr)), f"{name}: non-finite entries")
        arr = runtime_check(
            arr, jnp.any(norm == 0), f"{name}: zero {what}, which is no rotation"
        )
        arr = runtime_check(
            arr, ~jnp.all(jnp.abs(norm - 1) <= tol_),
            f"{name}: {what} of non-unit norm (| |q| - 1 | > {tol_:g}); project with "
            f"{type(self).__name__}(data).normalize() or pass a larger tol",
        )
        if self.scale_index is not None:
            arr = runtime_check(
                arr, ~jnp.all(arr[..., self.scale_index] > 0), f"{name}: scale s must be > 0"
            )
        return arr

    # -- shape helpers -------------------------------------------------------------
    def reshape(self: G, *shape: int) -> G:
        """Reshape the batch axes (the storage axis is kept): ``X.reshape(2, 3)``."""
        shape = _shape_args(shape)
        return type(self)(self.data.reshape(*shape, self.storage_dim))

    def broadcast_to(self: G, shape: int | Sequence[int]) -> G:
        """Broadcast to batch ``shape`` (data shape ``(*shape, storage_dim)``)."""
        shape = as_batch_shape(shape, f"{type(self).__name__}.broadcast_to(shape)")
        return type(self)(jnp.broadcast_to(self.data, (*shape, self.storage_dim)))

    # -- constructors ----------------------------------------------------------------
    @classmethod
    def identity(cls: type[G], shape: int | Sequence[int] = (), dtype: Any = None) -> G:
        """Identity element with batch ``shape`` (an int ``n`` means ``(n,)``)."""
        shape = as_batch_shape(shape, f"{cls.__name__}.identity(shape)")
        dtype = jnp.result_type(float) if dtype is None else dtype
        if not jnp.issubdtype(dtype, jnp.floating):  # the constructor would promote it
            raise TypeError(f"{cls.__name__}.identity(dtype={dtype!r}): expected a floating "
                            f"dtype")
        ident = jnp.asarray(cls._identity_data(), dtype)
        return cls(jnp.broadcast_to(ident, (*shape, cls.storage_dim)))

    @classmethod
    def exp(cls: type[G], a: Any) -> G:
        """Exponential map from a tangent vector (array or algebra element)."""
        data = _tangent_data(a, cls.algebra, f"{cls.__name__}.exp(a)")
        return cls(cls._exp(data))

    Exp = exp

    @classmethod
    def random(
        cls: type[G], key: Array, shape: int | Sequence[int] = (), sigma: float = 1.0,
        dtype: Any = None,
    ) -> G:
        """``Exp(σ·n)`` with n ~ N(0, I) in the tangent space (explicit PRNG ``key``); an
        int ``shape`` ``n`` means ``(n,)``. ``sigma``: one std for every tangent coordinate
        or one per coordinate ``(tangent_dim,)`` (PyPose's ``randn_*`` use σ/√3 on each
        rotation-vector axis)."""
        if not (isinstance(key, jax.Array) and (key.dtype == jnp.uint32 or
                                                 jnp.issubdtype(key.dtype, jax.dtypes.prng_key))):
            raise TypeError(f"{cls.__name__}.random(key): expected a jax.random key, got {key!r}")
        shape = as_batch_shape(shape, f"{cls.__name__}.random(shape)")
        dtype = jnp.result_type(float) if dtype is None else dtype
        n = jax.random.normal(key, (*shape, cls.tangent_dim), dtype)
        return cls(cls._exp(jnp.asarray(sigma, dtype) * n))

    @classmethod
    def from_matrix(cls: type[G], matrix: Any, check: bool = True, tol: float | None = None) -> G:
        """From a (…, n, n) matrix.

        ``check=True`` verifies, per element and at run time (:func:`equinox.error_if`, so
        also under ``jit``), that the rotation block alone is a (scaled, for Sim3 / RxSO3)
        rotation with det > 0 to ``tol`` relative to its own size (default 1e-9 float64,
        1e-5 float32) — a large translation does not widen the tolerance — that the
        bottom row is ``[0 … 0 1]`` and that every entry is finite. ``check=False``
        maps any matrix onto the group instead: for 3-D rotations the normalised
        quaternion of Shepperd's method, which for a matrix off SO(3) by ε is within O(ε)
        of, but not, the nearest rotation in the Frobenius norm (scipy's; project with an
        SVD first where that matters)."""
        m = as_float_array(matrix, f"{cls.__name__}.from_matrix(matrix)")
        n = cls.matrix_dim
        if m.ndim < 2 or m.shape[-2:] != (n, n):
            raise ValueError(
                f"{cls.__name__}.from_matrix(matrix): expected shape (..., {n}, {n}), "
                f"got {tuple(m.shape)}"
            )
        data = cls._from_matrix(m)
        if check and m.size:
            tol_ = _default_tol(m.dtype) if tol is None else tol
            p = cls.point_dim
            block = m[..., :p, :p]
            err = jnp.max(jnp.abs(cls._matrix(data)[..., :p, :p] - block), axis=(-2, -1))
            size = jnp.max(jnp.abs(block), axis=(-2, -1))
            bad = ~(err <= tol_ * size)  # also true for NaN; a zero block has size 0
            if n == p + 1:
                want = jnp.zeros(n, m.dtype).at[-1].set(1.0)
                bad = bad | ~(jnp.max(jnp.abs(m[..., p, :] - want), -1) <= tol_)
                bad = bad | ~jnp.all(jnp.isfinite(m[..., :p, p]), -1)
            scaled = " up to a scale" if cls.scale_index is not None else ""
            data = runtime_check(
                data, jnp.any(bad),
                f"{cls.__name__}.from_matrix(matrix): not a valid {cls.__name__} matrix "
                f"(rotation block not orthonormal{scaled} with det +1 to a relative "
                f"{tol_:g}, bottom row not [0 … 0 1], or non-finite entries); pass "
                f"check=False to project instead",
            )
        return cls(data)

    # -- core operations ---------------------------------------------------------------
    def log(self) -> LieAlgebra:
        """Logarithm map to the algebra (rotation angle in [0, π])."""
        return self.algebra(self._log(self.data))

    def Log(self) -> LieAlgebra:  # noqa: N802 - PyPose spelling
        """PyPose spelling of :meth:`log`."""
        return self.log()

    def inv(self: G) -> G:
        """Group inverse."""
        return type(self)(self._inv(self.data))

    def Inv(self: G) -> G:  # noqa: N802 - PyPose spelling
        """PyPose spelling of :meth:`inv`."""
        return self.inv()

    def compose(self: G, other: G) -> G:
        """Group product ``self · other`` (broadcast over batch axes)."""
        _check_same_type(self, other, f"{type(self).__name__}.compose")
        broadcast_batch(self.shape, other.shape, what=f"{type(self).__name__}.compose")
        return type(self)(self._compose(self.data, other.data))

    def act(self, points: Any) -> Array:
        """Act on points (…, p) or homogeneous points (…, p+1); p = point_dim."""
        name = f"{type(self).__name__}.act(points)"
        pts = as_float_array(points, name)
        p = self.point_dim
        check_last_dim(pts, (p, p + 1), name, f"[x, y{', z' if p == 3 else ''}(, w)]")
        broadcast_batch(self.shape, pts.shape[:-1], what=name)
        if pts.shape[-1] == p:
            return self._act(self.data, pts)
        return self._act_homogeneous(self.data, pts)

    def Act(self, points: Any) -> Array:  # noqa: N802 - PyPose spelling
        """PyPose spelling of :meth:`act`."""
        return self.act(points)

    def __matmul__(self, other: Any) -> Any:
        if isinstance(other, LieGroup):
            return self.compose(other)
        if isinstance(other, LieAlgebra):
            raise TypeError(
                f"{type(self).__name__} @ {type(other).__name__}: an algebra element is not "
                f"a group element or a point; use .exp() first or adj()"
            )
        return self.act(other)

    def __mul__(self, other: Any) -> Any:  # PyPose uses * for composition / action
        return self.__matmul__(other)

    def matrix(self) -> Array:
        """Matrix representation (…, n, n)."""
        return self._matrix(self.data)

    def adj_matrix(self) -> Array:
        """Adjoint matrix Adj(X) (…, d, d): X·Exp(a) = Exp(Adj(X) a)·X."""
        return self._adj_matrix(self.data)

    def adj(self, a: Any) -> LieAlgebra:
        """Adjoint action Adj(X)·a on an algebra element (or tangent array)."""
        data = _tangent_data(a, self.algebra, f"{type(self).__name__}.adj(a)")
        broadcast_batch(self.shape, data.shape[:-1], what=f"{type(self).__name__}.adj(a)")
        return self.algebra(matvec(self.adj_matrix(), data))

    def Adj(self, a: Any) -> LieAlgebra:  # noqa: N802 - PyPose spelling
        """PyPose spelling of :meth:`adj`."""
        return self.adj(a)

    def adjT(self, a: Any) -> LieAlgebra:  # noqa: N802 - PyPose name
        """Transposed adjoint action Adj(X)ᵀ·a."""
        data = _tangent_data(a, self.algebra, f"{type(self).__name__}.adjT(a)")
        broadcast_batch(self.shape, data.shape[:-1], what=f"{type(self).__name__}.adjT(a)")
        return self.algebra(matvec(jnp.swapaxes(self.adj_matrix(), -1, -2), data))

    def AdjT(self, a: Any) -> LieAlgebra:  # noqa: N802 - PyPose name and semantics
        """PyPose's ``AdjT``: ``Adj(X⁻¹)·a``, defined by ``Exp(a)·X = X·Exp(AdjT a)``.

        Equal to :meth:`adjT` (the transpose ``Adj(X)ᵀ·a``) where Adj(X) is orthogonal
        (SO3, SO2, RxSO3), different on SE3, Sim3 and SE2; kept under PyPose's name with
        PyPose's values so ported code gives the same numbers."""
        data = _tangent_data(a, self.algebra, f"{type(self).__name__}.AdjT(a)")
        broadcast_batch(self.shape, data.shape[:-1], what=f"{type(self).__name__}.AdjT(a)")
        return self.algebra(matvec(self._adj_matrix(self._inv(self.data)), data))

    def jinvp(self, a: Any) -> LieAlgebra:
        """``Jl⁻¹(Log X) · a`` (PyPose's ``Jinvp``)."""
        data = _tangent_data(a, self.algebra, f"{type(self).__name__}.jinvp(a)")
        broadcast_batch(self.shape, data.shape[:-1], what=f"{type(self).__name__}.jinvp(a)")
        return self.algebra(matvec(self._jl_inv(self._log(self.data)), data))

    Jinvp = jinvp

    def normalize(self: G) -> G:
        """Project the stored data back onto the group (unit quaternions etc.)."""
        return type(self)(self._normalize(self.data))

    def interpolate(self: G, other: G, t: Any) -> G:
        """Geodesic interpolation ``X · Exp(t · Log(X⁻¹ Y))``; t = 0 → X, t = 1 → Y.

        ``t`` broadcasts with the batch shape."""
        name = f"{type(self).__name__}.interpolate"
        _check_same_type(self, other, name)
        tt = jnp.asarray(t, self.dtype)
        broadcast_batch(self.shape, other.shape, tt.shape, what=f"{name} (x, other, t)")
        delta = self._log(self._compose(self._inv(self.data), other.data))
        return type(self)(self._compose(self.data, self._exp(tt[..., None] * delta)))

    def retract(self: G, delta: Any) -> G:
        """Right retraction ``X ⊕ δ = X · Exp(δ)``."""
        return self._times_exp(delta, self._exp, "retract")

    def retract_linear(self: G, delta: Any) -> G:
        """``X · E(δ)`` with ``E`` the first-order Taylor polynomial of ``Exp`` at 0: the
        value and the first derivative in δ at δ = 0 equal :meth:`retract`'s, so a
        Jacobian taken there (and its derivatives of any order with respect to X or
        anything else) is exact, from a much smaller program than ``Exp``'s. ``E(δ)``
        leaves the manifold for δ ≠ 0: use it only inside a first derivative in δ at
        δ = 0, never for a step or for second derivatives in δ."""
        return self._times_exp(delta, self._exp_linear, "retract_linear")

    def retract_quadratic(self: G, delta: Any) -> G:
        """``X · E₂(δ)`` with ``E₂`` the second-order Taylor polynomial of ``Exp`` at 0:
        :meth:`retract_linear`'s contract one order higher (value, first and second
        derivatives in δ at δ = 0 equal :meth:`retract`'s), for exact Hessians in the
        tangent chart. Never for a step or third derivatives in δ."""
        return self._times_exp(delta, self._exp_quadratic, "retract_quadratic")

    def _times_exp(self: G, delta: Any, exp: Any, method: str) -> G:
        """``X · exp(δ)`` for the retractions (``method`` names the caller in errors)."""
        name = f"{type(self).__name__}.{method}(delta)"
        data = _tangent_data(delta, self.algebra, name)
        broadcast_batch(self.shape, data.shape[:-1], what=name)
        return type(self)(self._compose(self.data, exp(data)))

    @classmethod
    def _exp_linear(cls, delta: Array) -> Array:
        """First-order Taylor polynomial of ``_exp`` at 0 (storage layout); groups give
        it in closed form, this default is ``_exp`` itself (exact to every order)."""
        return cls._exp(delta)

    @classmethod
    def _exp_quadratic(cls, delta: Array) -> Array:
        """Second-order Taylor polynomial of ``_exp`` at 0 (as :meth:`_exp_linear`)."""
        return cls._exp(delta)

    def rminus(self, other: LieGroup) -> Array:
        """Right minus ``Log(other⁻¹ · self)`` so that ``other ⊕ (self ⊖ other) = self``."""
        _check_same_type(self, other, f"{type(self).__name__}.rminus")
        broadcast_batch(self.shape, other.shape, what=f"{type(self).__name__}.rminus")
        return self._log(self._compose(self._inv(other.data), self.data))

    def cumprod(self: G, axis: int = 0, left: bool = True) -> G:
        """Cumulative product along a batch ``axis`` with ``jax.lax.associative_scan``.

        ``left=True`` (PyPose's default): Yᵢ = Xᵢ·…·X₁·X₀;
        ``left=False``: Yᵢ = X₀·X₁·…·Xᵢ (chaining relative motions, odometry)."""
        nb = len(self.shape)
        if not -nb <= axis < nb:
            raise ValueError(
                f"{type(self).__name__}.cumprod(axis={axis}): axis out of range for batch "
                f"shape {self.shape}"
            )
        ax = axis % nb

        def op(a: Array, b: Array) -> Array:
            return self._compose(b, a) if left else self._compose(a, b)

        return type(self)(jax.lax.associative_scan(op, self.data, axis=ax))

    # -- components (overridden where they exist) -------------------------------------
    def translation(self) -> Array:
        """Translation (…, point_dim); zeros for rotation-only groups."""
        return jnp.zeros((*self.shape, self.point_dim), self.dtype)

    def scale(self) -> Array:
        """Scale (…,); ones for groups without a scale."""
        return jnp.ones(self.shape, self.dtype)

    # -- defaults for raw functions ------------------------------------------------------
    @classmethod
    def _act_homogeneous(cls, data: Array, p: Array) -> Array:
        d = cls.point_dim
        m = cls._matrix(data)  # (..., n, n)
        if cls.matrix_dim == d:  # rotation-only groups: act on the first d entries
            return jnp.concatenate([matvec(m, p[..., :d]), p[..., d:]], -1)
        return matvec(m, p)

    @classmethod
    def _normalize(cls, data: Array) -> Array:
        return cls._from_matrix(cls._matrix(data))

    @classmethod
    def _jl(cls, a: Array) -> Array:
        """Generic left Jacobian ∫₀¹ Ad(Exp(u a)) du by Gauss–Legendre quadrature."""
        u = jnp.asarray(GL_NODES, a.dtype)
        w = jnp.asarray(GL_WEIGHTS, a.dtype)
        ad = cls._adj_matrix(cls._exp(a[..., None, :] * u[:, None]))  # (..., N, d, d)
        return jnp.einsum("...nij,n->...ij", ad, w, precision=FULL)

    @classmethod
    def _jl_inv(cls, a: Array) -> Array:
        jl = cls._jl(a)
        eye = jnp.broadcast_to(jnp.eye(cls.tangent_dim, dtype=a.dtype), jl.shape)
        return jnp.linalg.solve(jl, eye)

    @classmethod
    def _jl_inv_principal(cls, a: Array) -> Array:
        """``_jl_inv`` for a tangent from ``_log`` (rotation angle ≤ π): groups whose
        coefficients have a shorter form on that range (SO3, SE3, SE2) override it."""
        return cls._jl_inv(a)

    @classmethod
    def _jl_inv_principal_dual(cls, a: Array, y: Array) -> tuple[Array, Array, Array]:
        """``(J, Jᵀy, ∂(Jᵀy)/∂a)`` with J = ``_jl_inv_principal(a)`` (d, d), for one
        tangent ``a`` (d,) and a fixed ``y`` (d,): what the exact Hessian of a between
        factor needs (forward mode here; SE3 and SE2 override it with closed forms)."""
        def jty(x: Array) -> tuple[Array, tuple[Array, Array]]:
            jac = cls._jl_inv_principal(x)
            out = jnp.sum(jac * y[:, None], 0)
            return out, (out, jac)

        dual, (out, jac) = jax.jacfwd(jty, has_aux=True)(a)
        return jac, out, dual


def _shape_args(shape: tuple[Any, ...]) -> tuple[int, ...]:
    """Accept reshape(2, 3) and reshape((2, 3))."""
    if len(shape) == 1 and isinstance(shape[0], (tuple, list)):
        return tuple(shape[0])
    return tuple(shape)


def _axes_used(i: Any) -> int:
    """How many batch axes one index entry consumes (numpy rules)."""
    if i is None or i is Ellipsis or isinstance(i, (bool, np.bool_)):
        return 0
    dtype = getattr(i, "dtype", None)
    if dtype is not None and jnp.issubdtype(dtype, jnp.bool_):
        return max(np.ndim(i), 1) if np.ndim(i) else 0
    return 1


def _check_bounds(i: Any, axis: int, x: Any, idx: Any) -> None:
    """IndexError for an out-of-range integer index known in Python (JAX would clamp):
    Python and NumPy integers, integer lists, NumPy and concrete JAX arrays. A traced
    index (under ``jit``/``vmap``) is not known and follows JAX's clamping."""
    if isinstance(i, (bool, np.bool_)):
        return
    concrete_jax = (
        isinstance(i, jax.Array) and not isinstance(i, jax.core.Tracer)
        and i.is_fully_addressable
    )
    if isinstance(i, (int, np.integer)) or (
        (isinstance(i, np.ndarray) or concrete_jax) and jnp.issubdtype(i.dtype, jnp.integer)
    ):
        vals = np.asarray(i)
    elif isinstance(i, list) and i and all(
        isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in i
    ):
        vals = np.asarray(i)
    else:
        return  # slices, traced arrays, boolean masks
    n = x.shape[axis]
    if vals.size and not (vals.min() >= -n and vals.max() < n):
        bad = vals[(vals < -n) | (vals >= n)].flat[0]
        raise IndexError(
            f"{type(x).__name__}[{idx!r}]: index {bad} is out of range for batch axis "
            f"{axis} of size {n} (batch shape {x.shape})"
        )


def _batch_index(idx: Any, x: Any) -> Any:
    """Index only the batch axes of ``data`` (never the storage axis). Integer indices
    known in Python are bounds-checked (JAX clamps them silently), so iteration ends."""
    idx_t = idx if isinstance(idx, tuple) else (idx,)
    if not x.shape and any(i is not Ellipsis and i is not None for i in idx_t):
        raise IndexError(
            f"{type(x).__name__}[{idx!r}]: the element is unbatched (batch shape ()), "
            f"there is no batch axis to index"
        )
    n_ell = sum(i is Ellipsis for i in idx_t)
    if n_ell > 1:
        raise IndexError(f"{type(x).__name__}[{idx!r}]: an index can only have one ellipsis")
    pos = idx_t.index(Ellipsis) if n_ell else len(idx_t)
    left, right = idx_t[:pos], idx_t[pos + 1:]
    used = sum(_axes_used(i) for i in idx_t)
    if used > len(x.shape):
        raise IndexError(
            f"{type(x).__name__}[{idx!r}]: too many indices for batch shape {x.shape} "
            f"(the last data axis is the element itself and is not indexed)"
        )
    axis = 0
    for i in left:
        _check_bounds(i, axis, x, idx)
        axis += _axes_used(i)
    axis = len(x.shape) - sum(_axes_used(i) for i in right)
    for i in right:
        _check_bounds(i, axis, x, idx)
        axis += _axes_used(i)
    if n_ell:
        return (*idx_t, slice(None))
    return (*idx_t, Ellipsis)


def _tangent_data(a: Any, algebra: type[LieAlgebra], argname: str) -> Array:
    if isinstance(a, LieAlgebra):
        if not isinstance(a, algebra):
            raise TypeError(f"{argname}: expected {algebra.__name__}, got {type(a).__name__}")
        return a.data
    if isinstance(a, LieGroup):
        raise TypeError(f"{argname}: expected a tangent vector, got group {type(a).__name__}")
    arr = as_float_array(a, argname)
    check_last_dim(arr, algebra.tangent_dim, argname, algebra.layout)
    return arr
