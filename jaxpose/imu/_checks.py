"""Input validation for the IMU functions (internal): trace-time shape and type checks
with messages naming the function and argument, and run-time value checks through
:func:`equinox.error_if` (under tracing) or returned flags (an eager call raises
:class:`~jaxpose.lie.InvalidValueError` from them after the compiled call)."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array as as_float
from ..lie import InvalidValueError
from ..lie._base import runtime_check

Array = jax.Array


def _non_negative(arr: Array, name: str) -> Array:
    """Refuse a negative σ (squared, it would silently act as |σ|): eagerly with its
    value, a traced σ (e.g. learned) in the compiled program (``runtime_check``)."""
    what = f"{name}: expected σ ≥ 0 (a standard deviation"
    msg = (f"{what}; checked under jit)" if isinstance(arr, jax.core.Tracer)
           else f"{what}), got {np.asarray(arr)}")
    return runtime_check(arr, jnp.any(arr < 0), msg)


def scalar_var(x: Any, name: str, dtype: Any) -> Array:
    """A scalar σ ≥ 0 → σ²."""
    arr = as_float(x, name).astype(dtype)
    if arr.ndim != 0:
        raise ValueError(f"{name}: expected a scalar σ, got shape {tuple(arr.shape)}")
    arr = _non_negative(arr, name)
    return arr * arr


def noise_sigma(x: Any, name: str, dtype: Any) -> Array:
    """σ ≥ 0 (scalar or (3,)) → (3,)."""
    arr = as_float(x, name).astype(dtype)
    if arr.shape not in ((), (3,)):
        raise ValueError(f"{name}: expected a scalar σ or shape (3,), got {tuple(arr.shape)}")
    return jnp.broadcast_to(_non_negative(arr, name), (3,))


def check_samples(
    gyro: Any, acc: Any, dt: Any, fn: str
) -> tuple[Array, Array, Array, tuple[int, ...], Any]:
    """Validate shapes (trace time): gyro, acc (…, N, 3) with equal N; dt scalar, (N,) or
    (…, N). Returns the float arrays (not yet broadcast), the broadcast batch shape and
    the common dtype."""
    g = as_float(gyro, f"{fn}(gyro)")
    a = as_float(acc, f"{fn}(acc)")
    for arr, name in ((g, "gyro"), (a, "acc")):
        if arr.ndim < 2 or arr.shape[-1] != 3:
            raise ValueError(f"{fn}({name}): expected samples of shape (..., N, 3), got "
                             f"{tuple(arr.shape)}")
    if g.shape[-2] != a.shape[-2]:
        raise ValueError(f"{fn}: gyro has {g.shape[-2]} samples but acc has "
                         f"{a.shape[-2]} (shapes {tuple(g.shape)} and {tuple(a.shape)})")
    if g.shape[-2] == 0:
        raise ValueError(f"{fn}(gyro, acc): expected at least one sample, got 0")
    n = g.shape[-2]
    d = as_float(dt, f"{fn}(dt)")
    if d.ndim >= 1 and d.shape[-1] != n:
        raise ValueError(f"{fn}(dt): expected a scalar or {n} time steps (one per sample) "
                         f"in the last axis, got shape {tuple(d.shape)}")
    dtype = jnp.result_type(g, a, d)  # arrays: a Python-scalar dt is weakly typed
    try:
        batch = tuple(np.broadcast_shapes(g.shape[:-2], a.shape[:-2], d.shape[:-1]))
    except ValueError as err:
        raise ValueError(f"{fn}: batch shapes of gyro {tuple(g.shape[:-2])}, acc "
                         f"{tuple(a.shape[:-2])} and dt {tuple(d.shape[:-1])} do not "
                         f"broadcast") from err
    return g, a, d, batch, dtype


def broadcast_samples(
    g: Array, a: Array, d: Array, batch: tuple[int, ...], dtype: Any
) -> tuple[Array, Array, Array]:
    """Cast to ``dtype`` and broadcast to (*batch, N, 3), (*batch, N)."""
    n = g.shape[-2]
    return (
        jnp.broadcast_to(g.astype(dtype), (*batch, n, 3)),
        jnp.broadcast_to(a.astype(dtype), (*batch, n, 3)),
        jnp.broadcast_to(d.astype(dtype), (*batch, n)),
    )


def _message(name: str, fn: str) -> str:
    if name in ("gyro", "acc"):
        return f"{fn}({name}): samples contain NaN or inf"
    if name == "dt":
        return (f"{fn}(dt): every time step must be positive and finite (found dt <= 0, "
                f"inf or NaN)")
    if name == "result":
        return (f"{fn}: the result overflows (not finite) although every input is finite: "
                f"samples, dt or noise densities of extreme magnitude (such as 1e200, or "
                f"|gyro·dt| beyond ~1e150)")
    return f"{fn}({name}): contains NaN or inf"


# the order in which an eager call reports failed checks (inputs before the result)
_ORDER = ("gyro", "acc", "dt", "gyro_bias", "acc_bias", "gyro_noise", "acc_noise",
          "integration_noise", "result")


def _check(x: Any, bad: Array, name: str, fn: str, flags: dict[str, Array] | None) -> Any:
    """``eqx.error_if(x, bad, message)``; with a dict ``flags`` (an eager call) record
    ``bad`` there instead, for :func:`raise_flagged` after the call."""
    if flags is None:
        return eqx.error_if(x, bad, _message(name, fn))
    flags[name] = bad
    return x


def raise_flagged(flags: dict[str, Any], fn: str) -> None:
    """Raise the first failed check of an eager call as a one-line
    :class:`~jaxpose.lie.InvalidValueError` (as the lie groups' eager checks do)."""
    flags = jax.device_get(flags)
    for name in _ORDER:
        if name in flags and bool(flags[name]):
            raise InvalidValueError(_message(name, fn))


def check_values(g: Array, a: Array, d: Array, fn: str,
                 flags: dict[str, Array] | None = None) -> tuple[Array, Array, Array]:
    """Run-time value checks with :func:`equinox.error_if` (also under jit/vmap), or
    recorded in ``flags`` (see :func:`_check`)."""
    g = _check(g, ~jnp.all(jnp.isfinite(g)), "gyro", fn, flags)
    a = _check(a, ~jnp.all(jnp.isfinite(a)), "acc", fn, flags)
    d = _check(d, ~jnp.all((d > 0) & jnp.isfinite(d)), "dt", fn, flags)
    return g, a, d


def check_finite_inputs(values: dict[str, Array | None], fn: str,
                        flags: dict[str, Array] | None = None) -> dict[str, Array | None]:
    """Run-time check that optional inputs (noise densities, biases) are finite."""
    out: dict[str, Array | None] = {}
    for name, v in values.items():
        out[name] = None if v is None else _check(v, ~jnp.all(jnp.isfinite(v)), name, fn,
                                                  flags)
    return out


def check_outputs(out: Any, fn: str, flags: dict[str, Array] | None = None) -> Any:
    """Run-time check that the outputs computed from finite inputs are finite: extreme
    magnitudes (e.g. samples, dt or noise densities of 1e200) overflow somewhere in the
    rotation, the deltas, the covariance or the bias Jacobians."""
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(out)]
    bad = ~jnp.all(jnp.stack(leaves))
    return _check(out, bad, "result", fn, flags)


def biases(gyro_bias: Any, acc_bias: Any, batch: tuple[int, ...],
           fn: str) -> tuple[Array | None, Array | None, tuple[int, ...]]:
    """Validate the bias shapes ((3,) or (…, 3), None = zero); returns them unbroadcast
    and the batch shape broadcast with theirs."""
    out: list[Array | None] = []
    shapes = [batch]
    for b, name in ((gyro_bias, "gyro_bias"), (acc_bias, "acc_bias")):
        if b is None:
            out.append(None)
            continue
        arr = as_float(b, f"{fn}({name})")
        if arr.ndim == 0 or arr.shape[-1] != 3:
            raise ValueError(f"{fn}({name}): expected shape (3,) or (..., 3), got "
                             f"{tuple(arr.shape)}")
        out.append(arr)
        shapes.append(arr.shape[:-1])
    try:
        batch = tuple(np.broadcast_shapes(*shapes))
    except ValueError as err:
        raise ValueError(f"{fn}: bias batch shapes {[tuple(s) for s in shapes[1:]]} do not "
                         f"broadcast with the samples' batch shape {batch}") from err
    return out[0], out[1], batch
