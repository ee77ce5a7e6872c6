"""Conversions to and from jaxlie objects and PyPose ``LieTensor`` / torch tensors.

Neither peer is a dependency: each is imported lazily, inside the function that needs it,
and a missing one raises ``ImportError`` naming the package to install.

Layouts (``docs/conventions.md``). jaxpose stores PyPose's layouts, so PyPose arrays move
unchanged; jaxlie stores quaternions scalar-first and puts the rotation before the
translation, so the conversion reorders the storage explicitly:

| group | jaxpose ``.data`` | jaxlie ``.parameters()`` |
|---|---|---|
| SO3 | ``[qx, qy, qz, qw]`` | ``wxyz = [qw, qx, qy, qz]`` |
| SE3 | ``[tx, ty, tz, qx, qy, qz, qw]`` | ``wxyz_xyz = [qw, qx, qy, qz, tx, ty, tz]`` |
| SO2 | ``[cos θ, sin θ]`` | ``unit_complex = [cos θ, sin θ]`` |
| SE2 | ``[tx, ty, cos θ, sin θ]`` | ``unit_complex_xy = [cos θ, sin θ, tx, ty]`` |

Tangent vectors need no conversion: both libraries order twists translation first
(se3 ``[ρ(3), φ(3)]``, se2 ``[ρx, ρy, θ]``) and use the same ``Exp``, so
``to_jaxlie(jp.se3(v).exp()) == jaxlie.SE3.exp(v)``. Sim3 / RxSO3 have no jaxlie
counterpart; SO2 / SE2 have no PyPose counterpart (``TypeError``).

Batch axes are kept: a jaxpose element of data shape ``(*batch, n)`` becomes a jaxlie
object whose parameters have shape ``(*batch, n)`` (jaxlie ≥ 1.4 supports batch axes) or
a LieTensor of shape ``(*batch, n)``. Conversions to jaxlie are pure ``jnp`` reindexing,
so they jit, vmap and differentiate; conversions to torch copy through host memory
(or DLPack, zero-copy on the same device) and are for the boundary between programs.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import ml_dtypes
import numpy as np

from .lie import (
    SE2,
    SE3,
    SO2,
    SO3,
    LieAlgebra,
    LieGroup,
    RxSO3,
    Sim3,
    rxso3,
    se3,
    sim3,
    so3,
)

__all__ = [
    "from_jaxlie",
    "from_pypose",
    "from_torch",
    "to_jaxlie",
    "to_pypose",
    "to_torch",
]

# jaxpose storage index of each jaxlie parameter, per group (explicit, not computed).
_TO_JAXLIE_INDEX = {
    SO3: (3, 0, 1, 2),  # [qx qy qz qw] -> [qw qx qy qz]
    SE3: (6, 3, 4, 5, 0, 1, 2),  # [t q] -> [qw qx qy qz tx ty tz]
    SO2: (0, 1),  # [c s] -> [c s]
    SE2: (2, 3, 0, 1),  # [tx ty c s] -> [c s tx ty]
}
# The inverse permutations: jaxlie parameter index of each jaxpose storage entry.
_FROM_JAXLIE_INDEX = {
    SO3: (1, 2, 3, 0),  # [qw qx qy qz] -> [qx qy qz qw]
    SE3: (4, 5, 6, 1, 2, 3, 0),  # [qw qx qy qz tx ty tz] -> [tx ty tz qx qy qz qw]
    SO2: (0, 1),
    SE2: (2, 3, 0, 1),  # [c s tx ty] -> [tx ty c s]
}


def _jaxlie():
    try:
        import jaxlie
    except ImportError as err:  # pragma: no cover - exercised only without jaxlie
        raise ImportError("jaxpose.interop: jaxlie is not installed (pip install jaxlie)") from err
    return jaxlie


def _torch():
    try:
        import torch
    except ImportError as err:  # pragma: no cover - exercised only without torch
        raise ImportError("jaxpose.interop: torch is not installed (pip install torch)") from err
    return torch


def _pypose():
    try:
        import pypose
    except ImportError as err:  # pragma: no cover - exercised only without pypose
        raise ImportError(
            "jaxpose.interop: pypose is not installed (pip install pypose)"
        ) from err
    return pypose


# ----------------------------------------------------------------------------------
# jaxlie
# ----------------------------------------------------------------------------------
def to_jaxlie(x: LieGroup) -> Any:
    """jaxpose SO3 / SE3 / SO2 / SE2 (data ``(*batch, n)``) → the jaxlie group of the same
    batch shape, with the storage reordered as in the module table (jaxlie's quaternions
    are ``wxyz``). Jits, vmaps and differentiates (pure reindexing)."""
    jaxlie = _jaxlie()
    cls = type(x)
    if cls not in _TO_JAXLIE_INDEX:
        raise TypeError(
            f"to_jaxlie(x): expected an SO3, SE3, SO2 or SE2 element, got {cls.__name__}"
            + (" (jaxlie has no such group)" if cls in (Sim3, RxSO3) else "")
        )
    params = x.data[..., jnp.array(_TO_JAXLIE_INDEX[cls])]
    return getattr(jaxlie, cls.__name__)(params)


def from_jaxlie(x: Any) -> LieGroup:
    """jaxlie ``SO3`` / ``SE3`` / ``SO2`` / ``SE2`` (any batch shape) → the jaxpose group
    with PyPose storage (``SO3.data = [qx, qy, qz, qw]``, ``SE3.data = [t, q]``, ...)."""
    jaxlie = _jaxlie()
    for cls in _FROM_JAXLIE_INDEX:
        if isinstance(x, getattr(jaxlie, cls.__name__)):
            params = jnp.asarray(x.parameters())
            return cls(params[..., jnp.array(_FROM_JAXLIE_INDEX[cls])])
    raise TypeError(
        f"from_jaxlie(x): expected a jaxlie SO3, SE3, SO2 or SE2, got {type(x).__name__}"
    )


# ----------------------------------------------------------------------------------
# torch / PyPose
# ----------------------------------------------------------------------------------
def to_torch(x: Any) -> Any:
    """A JAX array (or a jaxpose element: its ``.data``) → a ``torch.Tensor`` of the same
    shape and dtype, sharing memory through DLPack where possible (CPU and same-device
    GPU arrays), else copied through host memory. A shared tensor must not be modified in
    place (``mul_``, ``+=``, ``out=``): that would change the JAX array, which JAX assumes
    immutable; ``.clone()`` it first (as :func:`to_pypose` does)."""
    torch = _torch()
    if isinstance(x, (LieGroup, LieAlgebra)):
        x = x.data
    if isinstance(x, jax.core.Tracer):
        raise TypeError("to_torch(x): got a traced value; convert outside jit/vmap/grad")
    arr = jnp.asarray(x)
    try:
        return torch.from_dlpack(arr)
    except (RuntimeError, TypeError, BufferError):
        return torch.from_numpy(np.array(arr))


def from_torch(t: Any, dtype: Any = None) -> jax.Array:
    """A ``torch.Tensor`` (a ``LieTensor`` too: its raw data) → a JAX array of the same
    shape; detached from torch's autograd. ``dtype`` casts. With JAX's x64 mode off,
    float64 becomes float32 (JAX's rule, silently) and int64 int32. Integers beyond the
    range of the integer dtype they end in raise instead of wrapping around."""
    torch = _torch()
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"from_torch(t): expected a torch.Tensor, got {type(t).__name__}")
    raw = t.detach()
    if hasattr(raw, "tensor"):  # LieTensor -> plain tensor
        raw = raw.tensor()
    # lazy conjugate / negative views cannot be read by .numpy(); bfloat16 has no NumPy
    # dtype in torch (its bits are read as ml_dtypes' bfloat16, JAX's)
    raw = raw.resolve_conj().resolve_neg().cpu().contiguous()
    if raw.dtype == torch.bfloat16:
        arr = raw.view(torch.int16).numpy().view(ml_dtypes.bfloat16)
    else:
        arr = raw.numpy()
    target = jax.dtypes.canonicalize_dtype(arr.dtype if dtype is None else dtype)
    if arr.dtype.kind in "iu" and target.kind in "iu" and arr.size:
        info = np.iinfo(target)
        if arr.min() < info.min or arr.max() > info.max:  # the cast would wrap them silently
            why = (" (JAX's x64 mode is off: enable it with "
                   'jax.config.update("jax_enable_x64", True) or pass a float dtype=)'
                   if np.dtype(arr.dtype if dtype is None else dtype) != target else
                   " (pass a wider or a float dtype=)")
            raise ValueError(f"from_torch(t): {arr.dtype} values beyond {target.name}'s range, "
                             f"where they would wrap around (2**40 → 0){why}")
    return jnp.asarray(arr.astype(target))


_PP_TYPES = {
    SO3: "SO3", SE3: "SE3", Sim3: "Sim3", RxSO3: "RxSO3",
    so3: "so3", se3: "se3", sim3: "sim3", rxso3: "rxso3",
}


def to_pypose(x: LieGroup | LieAlgebra, requires_grad: bool = False) -> Any:
    """jaxpose SO3 / SE3 / Sim3 / RxSO3 or so3 / se3 / sim3 / rxso3 → a PyPose
    ``LieTensor`` of the same ltype and data (layouts are identical; no reordering).
    SO2 / SE2 / so2 / se2 have no PyPose counterpart and raise ``TypeError``."""
    pp = _pypose()
    cls = type(x)
    if cls not in _PP_TYPES:
        raise TypeError(
            f"to_pypose(x): expected one of {', '.join(v for v in _PP_TYPES.values())}, "
            f"got {cls.__name__} (PyPose has no 2-D groups)"
        )
    data = to_torch(x.data).clone()  # a LieTensor owns its storage
    return getattr(pp, _PP_TYPES[cls])(data).requires_grad_(requires_grad)


def from_pypose(x: Any, dtype: Any = None) -> LieGroup | LieAlgebra:
    """PyPose ``LieTensor`` → the jaxpose element of the same ltype (``SO3_type`` →
    :class:`~jaxpose.SO3`, ``se3_type`` → :class:`~jaxpose.se3`, ...), data unchanged
    (detached); ``dtype`` casts as in :func:`from_torch`."""
    pp = _pypose()
    if not isinstance(x, pp.LieTensor):
        raise TypeError(f"from_pypose(x): expected a pypose.LieTensor, got {type(x).__name__}")
    for cls, name in _PP_TYPES.items():
        if x.ltype == getattr(pp, f"{name}_type"):
            return cls(from_torch(x, dtype))
    raise TypeError(f"from_pypose(x): unsupported ltype {x.ltype}")
