"""Module-level pure functions mirroring the group/algebra methods.

``jp.lie.log(X)`` is ``X.log()``, ``jp.lie.compose(X, Y)`` is ``X @ Y`` and so on; they
exist so pipelines can be written functionally (and so names match PyPose's
``pp.Exp``, ``pp.Log``, ...). Each checks its argument types and names them in errors.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp

from ._base import Array, LieAlgebra, LieGroup


def _group(x: Any, fn: str, arg: str = "x") -> LieGroup:
    if not isinstance(x, LieGroup):
        raise TypeError(f"{fn}({arg}): expected a Lie group element, got {type(x).__name__}")
    return x


def _algebra(a: Any, fn: str, arg: str = "a") -> LieAlgebra:
    if not isinstance(a, LieAlgebra):
        raise TypeError(f"{fn}({arg}): expected a Lie algebra element, got {type(a).__name__}")
    return a


def _group_type(cls: Any, fn: str) -> type[LieGroup]:
    if not (isinstance(cls, type) and issubclass(cls, LieGroup)):
        raise TypeError(f"{fn}(group): expected a group class such as SE3, got {cls!r}")
    return cls


def exp(a: LieAlgebra) -> LieGroup:
    """Exp: algebra element → group element."""
    return _algebra(a, "exp").exp()


def log(x: LieGroup) -> LieAlgebra:
    """Log: group element → algebra element (rotation angle in [0, π])."""
    return _group(x, "log").log()


def inv(x: LieGroup) -> LieGroup:
    """Group inverse X⁻¹; same type and batch shape as ``x``."""
    return _group(x, "inv").inv()


def compose(x: LieGroup, y: LieGroup) -> LieGroup:
    """x · y (same group type, broadcast batch shapes)."""
    return _group(x, "compose").compose(_group(y, "compose", "y"))


def act(x: LieGroup, points: Any) -> Array:
    """x acting on points (…, p) or homogeneous points (…, p+1)."""
    return _group(x, "act").act(points)


def adj(x: LieGroup, a: Any) -> LieAlgebra:
    """Adj(x)·a."""
    return _group(x, "adj").adj(a)


def adjT(x: LieGroup, a: Any) -> LieAlgebra:  # noqa: N802
    """Adj(x)ᵀ·a."""
    return _group(x, "adjT").adjT(a)


def jinvp(x: LieGroup, a: Any) -> LieAlgebra:
    """Jl⁻¹(Log x)·a (PyPose's Jinvp)."""
    return _group(x, "jinvp").jinvp(a)


def jr(a: LieAlgebra) -> Array:
    """Right Jacobian Jr(a) (…, d, d): Exp(a + δ) ≈ Exp(a)·Exp(Jr(a)·δ)."""
    return _algebra(a, "jr").jr()


def jl(a: LieAlgebra) -> Array:
    """Left Jacobian Jl(a) = Jr(−a) (…, d, d): Exp(a + δ) ≈ Exp(Jl(a)·δ)·Exp(a)."""
    return _algebra(a, "jl").jl()


def jr_inv(a: LieAlgebra) -> Array:
    """Inverse right Jacobian Jr(a)⁻¹ (…, d, d)."""
    return _algebra(a, "jr_inv").jr_inv()


def jl_inv(a: LieAlgebra) -> Array:
    """Inverse left Jacobian Jl(a)⁻¹ (…, d, d)."""
    return _algebra(a, "jl_inv").jl_inv()


def hat(a: LieAlgebra) -> Array:
    """Matrix form of an algebra element (…, n, n), e.g. [φ]× for so3."""
    return _algebra(a, "hat").hat()


def matrix(x: LieGroup | LieAlgebra) -> Array:
    """Matrix of a group element (…, n, n); for an algebra element, the matrix of ``Exp(a)``.

    n = 3 for SO3 / RxSO3 (``s·R``), 4 for SE3 / Sim3, 2 for SO2, 3 for SE2.
    """
    if isinstance(x, LieAlgebra):
        return x.matrix()
    return _group(x, "matrix").matrix()


def from_matrix(group: type[LieGroup], m: Any, check: bool = True) -> LieGroup:
    """Group element of type ``group`` from matrices (…, n, n).

    ``check=True`` verifies at run time (eagerly, or ``eqx.error_if`` under ``jit``) that
    the rotation block alone is orthonormal (up to the scale of Sim3 / RxSO3) with det +1
    relative to its own size, that the bottom row is ``[0 … 0 1]`` and that the entries are
    finite; ``check=False`` projects onto the group instead.
    """
    return _group_type(group, "from_matrix").from_matrix(m, check=check)


def identity(
    group: type[LieGroup], shape: int | Sequence[int] = (), dtype: Any = None
) -> LieGroup:
    """Identity element of ``group`` with batch ``shape`` (data shape ``(*shape, storage_dim)``;
    an int ``n`` means ``(n,)``)."""
    return _group_type(group, "identity").identity(shape, dtype)


def random(
    group: type[LieGroup], key: Array, shape: int | Sequence[int] = (), sigma: float = 1.0,
    dtype: Any = None,
) -> LieGroup:
    """Random elements ``Exp(σ·n)``, n ~ N(0, I) in the tangent space, batch ``shape``.

    ``key`` is an explicit ``jax.random`` key; ``sigma`` scales the tangent noise.
    """
    return _group_type(group, "random").random(key, shape, sigma, dtype)


def translation(x: LieGroup) -> Array:
    """Translation part (…, 2) or (…, 3); zeros for rotation-only groups."""
    return _group(x, "translation").translation()


def rotation(x: LieGroup) -> LieGroup:
    """Rotation part as SO3 (3D groups) or SO2 (planar groups); raises ``TypeError`` otherwise."""
    x = _group(x, "rotation")
    if not hasattr(x, "rotation"):
        raise TypeError(f"rotation(x): {type(x).__name__} has no rotation part")
    return x.rotation()


def scale(x: LieGroup) -> Array:
    """Scale s (…,) of Sim3 / RxSO3; ones for the other groups."""
    return _group(x, "scale").scale()


def euler(x: LieGroup) -> Array:
    """Roll-pitch-yaw ``[r, p, y]`` (…, 3) of a 3D rotation, R = Rz(y)·Ry(p)·Rx(r)."""
    x = _group(x, "euler")
    if not hasattr(x, "euler"):
        raise TypeError(f"euler(x): {type(x).__name__} has no 3D rotation")
    return x.euler()


def from_euler(e: Any) -> LieGroup:
    """SO3 from roll-pitch-yaw ``e`` (…, 3), R = Rz(y)·Ry(p)·Rx(r) (PyPose's ``euler2SO3``)."""
    from ._so3 import SO3

    return SO3.from_euler(e)


def normalize(x: LieGroup) -> LieGroup:
    """Project the stored data back onto the group (unit quaternions, unit complex numbers)."""
    return _group(x, "normalize").normalize()


def interpolate(x: LieGroup, y: LieGroup, t: Any) -> LieGroup:
    """Geodesic interpolation ``x·Exp(t·Log(x⁻¹·y))``; ``t`` (…,) broadcasts with the batch."""
    return _group(x, "interpolate").interpolate(_group(y, "interpolate", "y"), t)


def cumprod(x: LieGroup, axis: int = 0, left: bool = True) -> LieGroup:
    """Cumulative product along batch ``axis`` (``jax.lax.associative_scan``).

    ``left=True``: Yᵢ = Xᵢ·…·X₀ (PyPose's default); ``left=False``: Yᵢ = X₀·…·Xᵢ.
    """
    return _group(x, "cumprod").cumprod(axis, left)


def stack(xs: Sequence[LieGroup], axis: int = 0) -> LieGroup:
    """Stack same-type elements along a new batch axis."""
    if not xs:
        raise ValueError("stack(xs): expected a non-empty sequence")
    t = type(_group(xs[0], "stack", "xs[0]"))
    for i, x in enumerate(xs):
        if type(x) is not t:
            raise TypeError(f"stack(xs): xs[{i}] is {type(x).__name__}, expected {t.__name__}")
    nb = len(xs[0].shape)
    ax = axis % (nb + 1)
    return t(jnp.stack([x.data for x in xs], ax))


def tree_stack(trees: Sequence[Any]) -> Any:
    """Stack a sequence of equal-structure pytrees leaf-wise (axis 0)."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)
