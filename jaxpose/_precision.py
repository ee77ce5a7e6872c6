"""Full float32 precision for jaxpose's matrix products on every backend (internal).

JAX lets accelerators multiply float32 matrices in reduced-precision passes by default
(TF32 on NVIDIA GPUs since Ampere, bfloat16 passes on TPUs: about three significant
digits), while the CPU, PyTorch and PyPose keep full float32. jaxpose's solvers,
covariances, filters and controllers are specified to the dtype's precision, so their
bodies are traced under ``jax.default_matmul_precision("float32")``: every matrix product
in the program (and in its derivatives, which inherit each product's precision) is a full
float32 one. No effect on the CPU or on float64; the user's own code outside jaxpose keeps
the user's setting.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, TypeVar

import jax

F = TypeVar("F", bound=Callable[..., Any])

MATMUL_PRECISION = "float32"  # the context's name for it
FULL = jax.lax.Precision.HIGHEST  # the same, for a product's own ``precision=``


def full_precision(fn: F) -> F:
    """``fn`` traced (or run) under ``jax.default_matmul_precision("float32")``. Put it
    beneath ``jax.jit`` / ``eqx.filter_jit``, so the setting applies while the body is
    traced and is not part of the caller's compilation-cache key."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with jax.default_matmul_precision(MATMUL_PRECISION):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
