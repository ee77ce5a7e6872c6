"""Session set-up: float64 enabled (tests pass dtypes explicitly to cover float32), and the
repository root importable so the example scripts (``notebooks/_examples``) and the
benchmark (``bench/imu.py``) can be smoke-tested."""

import os
import sys

import jax

jax.config.update("jax_enable_x64", True)

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)
