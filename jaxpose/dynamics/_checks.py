"""Argument validation shared by dynamics, filters and control.

Shape and type checks run at trace time. Value checks (positive semi-definiteness,
finiteness) run only on concrete arrays: under ``jit``/``grad`` tracing the values are
unknown and the check is skipped (solvers then report a status instead).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array
from ..lie._base import runtime_check

Array = jax.Array


def is_concrete(x: Any) -> bool:
    """True when ``x`` holds known values (not a tracer)."""
    return not isinstance(x, jax.core.Tracer)


def as_array(x: Any, name: str, ndim: int | tuple[int, ...] | None = None) -> Array:
    """Floating JAX array with an optional exact ``ndim`` (or allowed set)."""
    arr = as_float_array(x, name)
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else ndim
        if arr.ndim not in allowed:
            want = " or ".join(str(d) for d in allowed)
            raise ValueError(
                f"{name}: expected an array with {want} dimensions, got shape {tuple(arr.shape)}"
            )
    return arr


def check_shape(arr: Array, shape: tuple[int | None, ...], name: str, what: str = "") -> None:
    """Exact shape check; ``None`` entries match any size."""
    ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape))
    if not ok:
        want = "(" + ", ".join("·" if s is None else str(s) for s in shape) + ")"
        extra = f" ({what})" if what else ""
        raise ValueError(f"{name}: expected shape {want}{extra}, got {tuple(arr.shape)}")


def check_last(arr: Array, size: int, name: str, what: str) -> None:
    """``arr.shape[-1] == size`` with an error naming the argument and its meaning."""
    if arr.ndim == 0 or arr.shape[-1] != size:
        raise ValueError(
            f"{name}: expected last dimension {size} ({what}), got shape {tuple(arr.shape)}"
        )


def _psd_limits(eps: float, scale: Any, k: int) -> tuple[Any, Any]:
    """(largest |M − Mᵀ|, lowest eigenvalue) that rounding alone gives a symmetric positive
    semi-definite k×k matrix whose largest entry is ``scale`` (≥ 1) in a dtype of
    precision ``eps``: one rule for the eager and the compiled check."""
    return 1e3 * eps * scale, -1e2 * eps * scale * k


def check_psd(mat: Array, name: str, *, strict: bool = False, symmetric: bool = True) -> None:
    """Raise if a concrete matrix (or stack) is not symmetric positive (semi-)definite.

    ``strict`` requires positive definiteness (covariances that are inverted);
    ``symmetric=False`` checks only the symmetric part (quadratic-form weights). Tolerances
    scale with the matrix norm and the dtype's precision."""
    if mat.ndim < 2 or mat.shape[-1] != mat.shape[-2]:
        raise ValueError(f"{name}: expected square matrices (..., k, k), got {tuple(mat.shape)}")
    if not is_concrete(mat):
        return
    m = np.asarray(mat, dtype=np.float64)
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name}: contains non-finite values")
    eps = float(jnp.finfo(mat.dtype).eps)
    scale = max(1.0, float(np.max(np.abs(m)))) if m.size else 1.0
    asym = float(np.max(np.abs(m - np.swapaxes(m, -1, -2)))) if m.size else 0.0
    max_asym, min_eig = _psd_limits(eps, scale, mat.shape[-1])
    if symmetric and asym > max_asym:
        raise ValueError(f"{name}: expected a symmetric matrix (max |M − Mᵀ| = {asym:.3g})")
    if m.size == 0:
        return
    w = np.linalg.eigvalsh(0.5 * (m + np.swapaxes(m, -1, -2)))
    lo = float(np.min(w))
    if strict and lo <= 0.0:
        raise ValueError(
            f"{name}: expected a positive-definite matrix, smallest eigenvalue {lo:.3g}"
        )
    if lo < min_eig:
        raise ValueError(
            f"{name}: expected a positive semi-definite matrix, smallest eigenvalue {lo:.3g}"
        )


def psd_checked(mat: Array, name: str, *, strict: bool = False) -> Array:
    """``mat`` after :func:`check_psd`; a traced matrix (under ``jit``/``vmap``) is
    checked in the compiled program instead (``eqx.error_if``: finite, symmetric, smallest
    eigenvalue as :func:`check_psd` tolerates, one ``eigvalsh``), so a covariance computed
    inside a jitted function is refused too. For matrices given once (noise, a starting
    covariance), not per step."""
    check_psd(mat, name, strict=strict)
    if is_concrete(mat) or mat.size == 0:
        return mat
    m = jax.lax.stop_gradient(mat)
    eps = float(jnp.finfo(mat.dtype).eps)
    finite = jnp.all(jnp.isfinite(m))
    safe = jnp.where(finite, m, 0.0)
    scale = jnp.maximum(1.0, jnp.max(jnp.abs(safe)))
    asym = jnp.max(jnp.abs(safe - jnp.swapaxes(safe, -1, -2)))
    lo = jnp.min(jnp.linalg.eigvalsh(0.5 * (safe + jnp.swapaxes(safe, -1, -2))))
    max_asym, min_eig = _psd_limits(eps, scale, mat.shape[-1])
    low = (lo <= 0.0) if strict else (lo < min_eig)
    bad = ~finite | (asym > max_asym) | low
    kind = "positive-definite" if strict else "positive semi-definite"
    return runtime_check(mat, bad, f"{name}: expected a finite, symmetric, {kind} matrix "
                                   f"(checked under jit)")


def check_finite(x: Array, name: str) -> None:
    """Raise on concrete non-finite values (no-op under tracing)."""
    if is_concrete(x) and not bool(jnp.all(jnp.isfinite(x))):
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")


def start_step(t0: Any, name: str = "t0") -> Any:
    """A start step: a Python int stays one (static, the common t0 = 0 slices as before);
    anything else becomes an int32 scalar array (traced under ``jit``: a new start does
    not recompile). Refuses non-integer and negative values (eagerly: a concrete 1.7
    would otherwise truncate to 1) and shapes other than a scalar."""
    if isinstance(t0, (int, np.integer)) and not isinstance(t0, bool):
        if t0 < 0:
            raise ValueError(f"{name}: expected a time step >= 0, got {int(t0)}")
        return int(t0)
    arr = jnp.asarray(t0)
    if arr.ndim != 0:
        raise ValueError(f"{name}: expected a scalar time step, got shape {tuple(arr.shape)}")
    if not jnp.issubdtype(arr.dtype, jnp.integer):
        if not jnp.issubdtype(arr.dtype, jnp.floating) or not is_concrete(arr) or (
                float(arr) != round(float(arr))):
            raise ValueError(f"{name}: expected an integer time step, got {t0!r}")
    return step_index(arr, name)


def window_message(steps: int, length: int, whose: str) -> str:
    """The error of a start step whose window of ``length`` steps leaves ``whose``
    ``steps`` time steps ("LTV system's")."""
    return (f"t0: expected 0 ≤ t0 ≤ {steps - length} (steps t0 … t0 + {length - 1} must "
            f"lie within the {whose} {steps} time steps)")


def step_window(arr: Array, t0: Any, length: int, what: str) -> Array:
    """``arr[t0 : t0 + length]`` along axis 0 for a start step ``t0`` (:func:`start_step`,
    possibly traced). Raises unless ``length`` ≤ len(arr) and 0 ≤ t0 ≤ len(arr) − length
    (eagerly, or by ``eqx.error_if`` under ``jit``): ``lax.dynamic_slice`` would silently
    clamp the start. ``what`` names the stack in the message ("LTV system's")."""
    k = arr.shape[0]
    if length > k:
        raise ValueError(f"horizon: {length} exceeds the {what} {k} time steps")
    if isinstance(t0, int):
        if t0 + length > k:
            raise ValueError(f"{window_message(k, length, what)}, got {t0}")
        return arr[t0:t0 + length]
    t0 = runtime_check(t0, t0 + length > k, window_message(k, length, what))
    return jax.lax.dynamic_slice_in_dim(arr, t0, length)


def step_index(t: Any, name: str = "t", steps: int | None = None, whose: str = "") -> Array:
    """``t`` as an int32 index into a stack of ``steps`` per-step arrays (``whose``: the
    stack's owner for the message, "LTV system's"). A negative, fractional or (given
    ``steps``) too large step raises (eagerly, or by ``eqx.error_if`` under ``jit``)
    instead of wrapping around to the last steps, being truncated or clamping to the
    last step, as JAX indexing would."""
    t = jnp.asarray(t)
    bad = t < 0
    if not jnp.issubdtype(t.dtype, jnp.integer):
        bad = bad | (t != jnp.round(t))
    bound = ""
    if steps is not None:
        bad = bad | (t >= steps)
        bound = f" and < {steps} (the {whose} {steps} time steps)"
    return runtime_check(
        t.astype(jnp.int32), jnp.any(bad), f"{name}: expected a time step index >= 0"
        f"{bound}, an integer (a negative step would wrap around to the last steps, a "
        f"fraction be truncated, a step past the last clamp to it)"
    )
