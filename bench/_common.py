"""Shared helpers for the benchmarks: timing, peer imports and markdown tables.

Timing rules (DESIGN.md, "Benchmarks"): compile time and steady-state time are reported
separately; every timed call ends with ``block_until_ready`` (JAX) so asynchronous
dispatch is not mistaken for speed; each measurement is repeated and the minimum (the
least disturbed by other load) and the median are kept.
"""

from __future__ import annotations

import importlib
import math
import os
import platform
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import jax


@dataclass(frozen=True)
class Timing:
    """Steady-state seconds per call (min and median over repeats) and compile seconds."""

    best: float
    median: float
    repeats: int
    number: int
    compile_s: float | None = None

    def rate(self, items: int) -> float:
        """Items per second at the best time."""
        return items / self.best


_CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}
_clock = time.perf_counter


def set_clock(kind: str) -> None:
    """``wall`` (default) or ``cpu``: process CPU time of all threads, which is robust to
    other load on a shared machine (best combined with :func:`pin_threads`)."""
    global _clock
    _clock = _CLOCKS[kind]


def pin_threads(n: int) -> None:
    """Run on ``n`` cores: CPU affinity (XLA sizes its thread pool from it when the
    backend starts) and torch's intra-op threads, if torch is installed."""
    cpus = sorted(os.sched_getaffinity(0))[:n]
    os.sched_setaffinity(0, cpus)
    try:
        import torch
    except ImportError:
        return
    torch.set_num_threads(n)


def _block(out: Any) -> Any:
    return jax.block_until_ready(out)


def _measure(
    call: Callable[[], Any], first_s: float, *, repeats: int, min_time: float,
    max_time: float,
) -> tuple[float, float, int, int]:
    """Time ``call`` (already warm; one call took ``first_s``): ``number`` calls per
    repeat so a repeat lasts about ``min_time``; stop once ``max_time`` is spent with at
    least 2 samples. A first call of over a second counts as a sample (saves time on the
    slowest cells, where one-off costs are negligible)."""
    number = max(1, math.ceil(min_time / max(first_s, 1e-9)))
    samples: list[float] = [first_s] if first_s > 1.0 else []
    spent = sum(samples)
    while len(samples) < repeats:
        t0 = _clock()
        for _ in range(number):
            call()
        dt = _clock() - t0
        samples.append(dt / number)
        spent += dt
        if spent > max_time and len(samples) >= 2:
            break
    return min(samples), statistics.median(samples), len(samples), number


def _timed(call: Callable[[], Any]) -> tuple[Any, float]:
    t0 = _clock()
    out = call()
    return out, _clock() - t0


def time_jax(
    fn: Callable[..., Any],
    *args: Any,
    repeats: int = 7,
    min_time: float = 0.05,
    max_time: float = 10.0,
) -> tuple[Timing, Any]:
    """Jit ``fn``, time compilation (lower + compile) and then steady-state calls.

    Returns the :class:`Timing` and the output of one call (for correctness checks)."""
    jitted = jax.jit(fn)
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    call = lambda: _block(compiled(*args))
    out, _ = _timed(call)  # first execution (page faults, thread-pool warm-up)
    _, first_s = _timed(call)
    best, med, reps, number = _measure(
        call, first_s, repeats=repeats, min_time=min_time, max_time=max_time
    )
    return Timing(best, med, reps, number, compile_s), out


def time_callable(
    fn: Callable[[], Any],
    *,
    repeats: int = 7,
    min_time: float = 0.05,
    max_time: float = 10.0,
    sync: Callable[[Any], Any] | None = None,
) -> tuple[Timing, Any]:
    """Time an eager callable (e.g. torch); ``sync`` waits for its result if needed."""
    sync = sync or (lambda x: x)
    call = lambda: sync(fn())
    out, _ = _timed(call)  # warm-up (allocator, thread pool)
    _, first_s = _timed(call)
    best, med, reps, number = _measure(
        call, first_s, repeats=repeats, min_time=min_time, max_time=max_time
    )
    return Timing(best, med, reps, number), out


# ----------------------------------------------------------------------------------
# Peers
# ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Peer:
    """An optional peer library: the module, or why it is skipped."""

    name: str
    module: Any | None
    version: str | None
    reason: str | None = None

    @property
    def available(self) -> bool:
        return self.module is not None

    def label(self) -> str:
        if self.available:
            return f"{self.name} {self.version}"
        return f"{self.name}: skipped: {self.reason}"


def import_peer(name: str, dist: str | None = None) -> Peer:
    """Import a peer library; a missing one is reported as skipped, never faked."""
    if os.environ.get("JAXPOSE_BENCH_SKIP", "") and name in os.environ[
        "JAXPOSE_BENCH_SKIP"
    ].split(","):
        return Peer(name, None, None, "disabled by JAXPOSE_BENCH_SKIP")
    try:
        mod = importlib.import_module(name)
    except ImportError as err:
        return Peer(name, None, None, f"{name} not installed ({err})")
    try:
        from importlib.metadata import version

        ver = version(dist or name)
    except Exception:  # noqa: BLE001 - version is informative only
        ver = getattr(mod, "__version__", "?")
    return Peer(name, mod, ver)


def environment() -> str:
    """One line describing the machine and library versions."""
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
        f"Python {platform.python_version()}, jax {jax.__version__} "
        f"({jax.default_backend()})"
    )


# ----------------------------------------------------------------------------------
# Formatting
# ----------------------------------------------------------------------------------
def fmt_rate(x: float | None) -> str:
    """Rate in compact scientific notation (``1.3e6``); '—' if missing."""
    if x is None or not math.isfinite(x):
        return "—"
    return f"{x:.2e}".replace("e+0", "e").replace("e+", "e").replace("e-0", "e-")


def fmt_batch(n: int) -> str:
    """Batch size: ``1e3`` for powers of ten, else the integer."""
    e = round(math.log10(n)) if n > 0 else 0
    return f"1e{e}" if n == 10**e and e >= 3 else str(n)


def fmt_ratio(a: float | None, b: float | None) -> str:
    """``a / b`` as ``12.3x``; '—' if either is missing."""
    if a is None or b is None or b == 0:
        return "—"
    r = a / b
    return f"{r:.1f}x" if r < 100 else f"{r:.0f}x"


def fmt_seconds(s: float | None) -> str:
    if s is None:
        return "—"
    return f"{s * 1e3:.0f} ms" if s < 1 else f"{s:.2f} s"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub markdown table (numbers right-aligned)."""
    cells = [[str(c) for c in row] for row in rows]
    align = [
        "---:" if cells and all(_numeric(r[i]) for r in cells) else "---"
        for i in range(len(header))
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(align) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in cells]
    return "\n".join(lines)


def _numeric(s: str) -> bool:
    s = s.strip()
    if s == "—":
        return True
    s = s.removesuffix("x").removesuffix(" ms").removesuffix(" s")
    try:
        float(s)
    except ValueError:
        return False
    return True


def emit_report(text: str, out: str | None) -> str:
    """Print a benchmark's markdown report, also write it to ``out`` (``--out``) when
    given, and return it."""
    print(text)
    if out:
        with open(out, "w", encoding="utf-8") as fh:
            fh.write(text + "\n")
    return text
