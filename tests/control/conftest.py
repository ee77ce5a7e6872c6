"""Session set-up: float64 enabled (tests pass dtypes explicitly to cover float32)."""

import jax

jax.config.update("jax_enable_x64", True)
