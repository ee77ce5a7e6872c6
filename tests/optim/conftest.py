"""Shared set-up for the optimiser tests.

float64 is enabled for the session; tests that exercise float32 pass float32 arrays
explicitly. XLA compilation dominates this suite's run time, so integration tests jit
one function per configuration and reuse it (e.g. for finite differences).
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)
