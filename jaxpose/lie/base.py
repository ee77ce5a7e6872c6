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

from collections.abc import Sequence
from typing import Any, ClassVar, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array
G = TypeVar("G", bound="LieGroup")
A = TypeVar("A", bound="LieAlgebra")


# ----------------------------------------------------------------------------------
# Validation helpers (trace-time: shapes and types only)
# ----------------------------------------------------------------------------------
def as_float_array(x: Any, argname: str) -> Array:
    """Convert ``x`` to a floating JAX array, with a clear error for non-arrays."""
    if isinstance(x, (LieGroup, LieAlgebra)):
        raise TypeError(
            f"{argname}: expected an array, got a {type(x).__name__} element; "
            f"use its `.data` if you meant the stored array"
        )
    if isinstance(x, (str, bytes, dict, set)) or x is None:
        raise TypeError(f"{argname}: expected an array-like of numbers, got {type(x).__name__}")
    try:
        arr = jnp.asarray(x)
    except (TypeError, ValueError) as err:
        raise TypeError(
            f"{argname}: expected an array-like of numbers, got {type(x).__name__}"
        ) from err
    if not jnp.issubdtype(arr.dtype, jnp.floating):
        if jnp.issubdtype(arr.dtype, jnp.complexfloating):
            raise TypeError(f"{argname}: expected a real floating array, got {arr.dtype}")
        arr = arr.astype(jnp.result_type(float))
    return arr


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


def _check_same_type(x: Any, y: Any, what: str) -> None:
    if type(x) is not type(y):
        raise TypeError(
            f"{what}: expected two {type(x).__name__} elements, got "
            f"{type(x).__name__} and {type(y).__name__}"
        )


def skew(v: Array) -> Array:
    """[v]× of shape (..., 3, 3) from v of shape (..., 3): [v]× p = v × p."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2
    )


def vee(m: Array) -> Array:
    """Inverse of :func:`skew`: (..., 3, 3) → (..., 3)."""
    return jnp.stack([m[..., 2, 1], m[..., 0, 2], m[..., 1, 0]], -1)


def matvec(m: Array, v: Array) -> Array:
    """Batched matrix-vector product (..., n, m) @ (..., m) → (..., n)."""
    return jnp.einsum("...ij,...j->...i", m, v)


# Gauss–Legendre nodes/weights on [0, 1], used for Jl(ξ) = ∫₀¹ Ad(Exp(uξ)) du on groups
# without a closed form (Sim3). Exact to float64 precision for |ξ| up to ~10.
_GL_N = 16
_gl_x, _gl_w = np.polynomial.legendre.leggauss(_GL_N)
GL_NODES = 0.5 * (_gl_x + 1.0)
GL_WEIGHTS = 0.5 * _gl_w


# ----------------------------------------------------------------------------------
# Lie algebra base
# ----------------------------------------------------------------------------------
class LieAlgebra(eqx.Module):
    """Element of a Lie algebra in vector form: ``data`` has shape (*batch, tangent_dim)."""

    data: Array

    tangent_dim: ClassVar[int]
    layout: ClassVar[str]
    group: ClassVar[type[LieGroup]]

    def __init__(self, data: Any):
        arr = as_float_array(data, f"{type(self).__name__}(data)")
        check_last_dim(arr, self.tangent_dim, f"{type(self).__name__}(data)", self.layout)
        self.data = arr

    # -- shape helpers -------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, ...]:
        """Batch shape (the data shape without the last axis)."""
        return tuple(self.data.shape[:-1])

    @property
    def dtype(self) -> Any:
        """Floating dtype of ``data``."""
        return self.data.dtype

    def __getitem__(self: A, idx: Any) -> A:
        return type(self)(self.data[_batch_index(idx, self)])

    def __len__(self) -> int:
        if not self.shape:
            raise TypeError("len() of an unbatched element")
        return self.shape[0]

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
class LieGroup(eqx.Module):
    """Element of a matrix Lie group: ``data`` has shape (*batch, storage_dim).

    Subclasses set the class constants and implement the raw array functions
    ``_exp, _log, _compose, _inv, _act, _matrix, _from_matrix, _adj_matrix, _jl,
    _jl_inv, _hat, _identity_data`` (all on plain arrays with broadcasting).
    """

    data: Array

    storage_dim: ClassVar[int]
    tangent_dim: ClassVar[int]
    matrix_dim: ClassVar[int]
    point_dim: ClassVar[int]  # 3 for 3D groups, 2 for planar ones
    layout: ClassVar[str]
    algebra: ClassVar[type[LieAlgebra]]

    def __init__(self, data: Any):
        arr = as_float_array(data, f"{type(self).__name__}(data)")
        check_last_dim(arr, self.storage_dim, f"{type(self).__name__}(data)", self.layout)
        self.data = arr

    # -- shape helpers -------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, ...]:
        """Batch shape (the data shape without the storage axis)."""
        return tuple(self.data.shape[:-1])

    @property
    def dtype(self) -> Any:
        """Floating dtype of ``data``."""
        return self.data.dtype

    def __getitem__(self: G, idx: Any) -> G:
        return type(self)(self.data[_batch_index(idx, self)])

    def __len__(self) -> int:
        if not self.shape:
            raise TypeError("len() of an unbatched element")
        return self.shape[0]

    def reshape(self: G, *shape: int) -> G:
        """Reshape the batch axes (the storage axis is kept): ``X.reshape(2, 3)``."""
        shape = _shape_args(shape)
        return type(self)(self.data.reshape(*shape, self.storage_dim))

    def broadcast_to(self: G, shape: Sequence[int]) -> G:
        """Broadcast to batch ``shape`` (data shape ``(*shape, storage_dim)``)."""
        return type(self)(jnp.broadcast_to(self.data, (*shape, self.storage_dim)))

    # -- constructors ----------------------------------------------------------------
    @classmethod
    def identity(cls: type[G], shape: Sequence[int] = (), dtype: Any = None) -> G:
        """Identity element with batch ``shape``."""
        dtype = jnp.result_type(float) if dtype is None else dtype
        ident = jnp.asarray(cls._identity_data(), dtype)
        return cls(jnp.broadcast_to(ident, (*tuple(shape), cls.storage_dim)))

    @classmethod
    def exp(cls: type[G], a: Any) -> G:
        """Exponential map from a tangent vector (array or algebra element)."""
        data = _tangent_data(a, cls.algebra, f"{cls.__name__}.exp(a)")
        return cls(cls._exp(data))

    Exp = exp

    @classmethod
    def random(
        cls: type[G], key: Array, shape: Sequence[int] = (), sigma: float = 1.0,
        dtype: Any = None,
    ) -> G:
        """``Exp(σ·n)`` with n ~ N(0, I) in the tangent space (explicit PRNG ``key``)."""
        if not (isinstance(key, jax.Array) and (key.dtype == jnp.uint32 or
                                                 jnp.issubdtype(key.dtype, jax.dtypes.prng_key))):
            raise TypeError(f"{cls.__name__}.random(key): expected a jax.random key, got {key!r}")
        dtype = jnp.result_type(float) if dtype is None else dtype
        n = jax.random.normal(key, (*tuple(shape), cls.tangent_dim), dtype)
        return cls(cls._exp(jnp.asarray(sigma, dtype) * n))

    @classmethod
    def from_matrix(cls: type[G], matrix: Any, check: bool = True, tol: float | None = None) -> G:
        """From a (…, n, n) matrix. ``check`` verifies the rotation block is orthogonal
        with determinant +1 (and the bottom row is [0…0 1]); values are checked at run time
        through :func:`equinox.error_if`, so it also works under ``jit``."""
        m = as_float_array(matrix, f"{cls.__name__}.from_matrix(matrix)")
        n = cls.matrix_dim
        if m.ndim < 2 or m.shape[-2:] != (n, n):
            raise ValueError(
                f"{cls.__name__}.from_matrix(matrix): expected shape (..., {n}, {n}), "
                f"got {tuple(m.shape)}"
            )
        data = cls._from_matrix(m)
        if check:
            tol_ = (1e-5 if m.dtype == jnp.float32 else 1e-9) if tol is None else tol
            err = jnp.max(jnp.abs(cls._matrix(data) - m)) if m.size else jnp.asarray(0.0)
            bound = tol_ * jnp.maximum(1.0, jnp.max(jnp.abs(m)) if m.size else 1.0)
            data = eqx.error_if(
                data, ~(err <= bound),  # also true for NaN (non-finite input or result)
                f"{cls.__name__}.from_matrix(matrix): not a valid {cls.__name__} matrix "
                f"(rotation block not orthonormal with det +1, or wrong structure); "
                f"pass check=False to project instead",
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
        name = f"{type(self).__name__}.retract(delta)"
        data = _tangent_data(delta, self.algebra, name)
        broadcast_batch(self.shape, data.shape[:-1], what=name)
        return type(self)(self._compose(self.data, self._exp(data)))

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
        return jnp.einsum("...nij,n->...ij", ad, w)

    @classmethod
    def _jl_inv(cls, a: Array) -> Array:
        jl = cls._jl(a)
        eye = jnp.broadcast_to(jnp.eye(cls.tangent_dim, dtype=a.dtype), jl.shape)
        return jnp.linalg.solve(jl, eye)


def _shape_args(shape: tuple[Any, ...]) -> tuple[int, ...]:
    """Accept reshape(2, 3) and reshape((2, 3))."""
    if len(shape) == 1 and isinstance(shape[0], (tuple, list)):
        return tuple(shape[0])
    return tuple(shape)


def _batch_index(idx: Any, x: Any) -> Any:
    """Index only the batch axes of ``data`` (never the storage axis)."""
    idx_t = idx if isinstance(idx, tuple) else (idx,)
    if not x.shape and any(i is not Ellipsis and i is not None for i in idx_t):
        raise IndexError(
            f"{type(x).__name__}[{idx!r}]: the element is unbatched (batch shape ()), "
            f"there is no batch axis to index"
        )
    if any(i is Ellipsis for i in idx_t):
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
