"""Shared helpers for the benchmarks: the command line, threads, worker subprocesses,
timing, peer imports and markdown tables.

Every script builds its parser on :func:`parser` (``--quick``, ``--out`` and
``--threads`` with one meaning and one default everywhere), reads ``--threads`` with
:func:`early_threads` before numpy/jax/torch start their thread pools, applies it with
:func:`set_threads`, and launches its ``--worker`` subprocesses with :func:`spawn_worker`
(the worker answers with :func:`worker_result`). This module imports jax lazily so that
:func:`early_threads` can run first. The registry of workloads is :mod:`bench.run`.

Timing rules (DESIGN.md, "Benchmarks"): compile time and steady-state time are reported
separately; every timed call ends with ``block_until_ready`` (JAX) so asynchronous
dispatch is not mistaken for speed; each measurement is repeated and the minimum (the
least disturbed by other load) and the median are kept.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent  # the repository (bench/..)
DEFAULT_THREADS = 1  # one thread per library: the fairest, most repeatable on a shared box
RESULT_TAG = "BENCH-RESULT "  # prefix of a worker's JSON answer on its stdout
WORKER_TIMEOUT = 1800.0  # seconds per worker subprocess


# ----------------------------------------------------------------------------------
# Command line and threads
# ----------------------------------------------------------------------------------
def parser(description: str | None, *, quick: str = "smoke-run settings (minutes)",
           threads: bool = True, clock: bool = True,
           workers: bool = False) -> argparse.ArgumentParser:
    """The common command line of every benchmark script: ``--quick`` (help text
    ``quick``, plain text: a ``%`` in it is literal), ``--out FILE.md``, with
    ``threads`` ``--threads N`` (default :data:`DEFAULT_THREADS`; 0 = each library's
    default) and, with ``threads`` and ``clock`` (scripts timing through
    :func:`time_jax`/:func:`time_callable`), ``--clock wall|cpu``; with ``workers``
    (scripts that run each contestant in a :func:`spawn_worker` subprocess)
    ``--timeout`` seconds per subprocess (default :data:`WORKER_TIMEOUT`)."""
    ap = argparse.ArgumentParser(description=(description or "").strip().split("\n")[0])
    ap.add_argument("--quick", action="store_true", help=quick.replace("%", "%%"))
    ap.add_argument("--out", default=None, help="also write the markdown report to this file")
    if threads:
        ap.add_argument("--threads", type=int, default=DEFAULT_THREADS,
                        help="CPU threads for jaxpose and each peer (BLAS/OpenMP pools, XLA's "
                        "Eigen pool, torch.set_num_threads); 0 = each library's default")
    if threads and clock:
        ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                        help="cpu: process CPU time, robust on a loaded machine (use with "
                        "--threads 1)")
    if workers:
        ap.add_argument("--timeout", type=float, default=WORKER_TIMEOUT,
                        help="seconds per worker subprocess")
    return ap


def early_threads(argv: Sequence[str] | None = None, default: int = DEFAULT_THREADS) -> int:
    """``--threads`` read from ``argv`` (default ``sys.argv[1:]``) before numpy, jax or
    torch load their BLAS/OpenMP thread pools, and those pools capped to it (environment
    variables, ``setdefault``): jaxlib's LAPACK kernels run on scipy's OpenBLAS and torch
    on its OpenMP/MKL pool, whose busy-waiting threads otherwise oversubscribe a shared
    machine. Call it at the top of a script run as ``__main__``. Returns the count."""
    argv = sys.argv[1:] if argv is None else argv
    threads = default
    for i, a in enumerate(argv):
        if a == "--threads" and i + 1 < len(argv):
            threads = int(argv[i + 1])
        elif a.startswith("--threads="):
            threads = int(a.split("=", 1)[1])
    if threads > 0:
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(var, str(threads))
    return threads


def script_threads(module: str) -> int:
    """A script's start-up, ``THREADS = script_threads(__name__)`` before numpy, jax or
    torch are imported: run as ``__main__``, :func:`early_threads` (pools capped to
    ``--threads``, which it returns); imported (tests, :mod:`bench.run`), nothing is
    changed and :data:`DEFAULT_THREADS` returned."""
    return early_threads() if module == "__main__" else DEFAULT_THREADS


def set_threads(threads: int, *, pin: bool = False) -> None:
    """The same thread budget for jaxpose and the peers (before JAX's first computation):
    XLA's Eigen pool off and ``torch.set_num_threads``; with ``pin`` also the CPU affinity
    (:func:`pin_threads`: XLA sizes its intra-op pool from it). 0 leaves the defaults."""
    if threads <= 0:
        return
    if pin:
        pin_threads(threads)
    flags = os.environ.get("XLA_FLAGS", "")
    if "--xla_cpu_multi_thread_eigen" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_multi_thread_eigen=false").strip()
    try:
        import torch
    except ImportError:
        return
    torch.set_num_threads(threads)


def torch_device() -> str:
    """Where the torch peers (PyPose) run: ``JAXPOSE_BENCH_TORCH_DEVICE`` when set, else
    ``cuda`` when torch sees a GPU (jaxpose then runs on it too: peers side by side on
    the same kind of device), else ``cpu``."""
    dev = os.environ.get("JAXPOSE_BENCH_TORCH_DEVICE")
    if dev:
        return dev
    try:
        import torch
    except ImportError:
        return "cpu"
    return "cuda" if torch.cuda.is_available() else "cpu"


def set_torch_device() -> str:
    """Make :func:`torch_device` torch's default device (factory calls inside PyPose
    included) and return it."""
    import torch

    dev = torch_device()
    torch.set_default_device(dev)
    return dev


def to_torch(a: Any) -> Any:
    """A copy of a numpy array as a torch tensor on :func:`torch_device` (same dtype; a
    copy, so in-place updates, e.g. of an optimiser's parameters, never reach ``a``)."""
    import numpy as np
    import torch

    return torch.tensor(np.ascontiguousarray(a), device=torch_device())


def to_numpy(t: Any) -> Any:
    """A torch tensor (any device) as a numpy array."""
    return t.detach().cpu().numpy()


def _torch_sync(out: Any) -> Any:
    """Wait for queued CUDA work when torch runs on a GPU (eager torch calls return
    before their kernels finish)."""
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()
    return out


def apply_common(args: argparse.Namespace, *, pin: bool = False) -> None:
    """Apply the common options of :func:`parser`: threads and the timing clock."""
    if hasattr(args, "threads"):
        set_threads(args.threads, pin=pin)
    if hasattr(args, "clock"):
        set_clock(args.clock)


# ----------------------------------------------------------------------------------
# Worker subprocesses
# ----------------------------------------------------------------------------------
def worker_result(payload: dict[str, Any]) -> None:
    """A worker's answer: one tagged JSON line on stdout (read by :func:`spawn_worker`)."""
    print(RESULT_TAG + json.dumps(payload), flush=True)


def spawn_worker(args: Sequence[str], *, timeout: float, env: dict[str, str] | None = None,
                 tail: int = 3) -> dict[str, Any]:
    """Run ``python ARGS`` (a script path or ``-m module``, then its ``--worker`` flags)
    from the repository root and return the worker's :func:`worker_result` dict plus
    ``wall_s``; ``{"failed": why}`` (with the last ``tail`` lines of its output) when it
    times out or exits without an answer. Each worker is its own process, so JIT caches,
    thread pools and peak memory (``ru_maxrss``) are its own."""
    t0 = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, *args], capture_output=True, text=True,
                              timeout=timeout, cwd=str(ROOT), env=env)
    except subprocess.TimeoutExpired:
        return {"failed": f"timed out after {timeout} s"}
    wall = time.perf_counter() - t0
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith(RESULT_TAG):
            out = json.loads(line[len(RESULT_TAG):])
            out.setdefault("wall_s", wall)
            return out
    lines = (proc.stderr or proc.stdout).strip().splitlines()[-tail:]
    return {"failed": f"exit {proc.returncode}: " + " / ".join(lines)}


@dataclass(frozen=True)
class Timing:
    """Steady-state seconds per call (min and median over repeats), compile seconds and,
    where asked for, the lines of the optimised HLO program (deterministic, unlike the
    seconds: it compares program sizes across machines)."""

    best: float
    median: float
    repeats: int
    number: int
    compile_s: float | None = None
    hlo_lines: int | None = None

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
    import jax

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
    compiler_options: dict[str, Any] | None = None,
    hlo_lines: bool = False,
) -> tuple[Timing, Any]:
    """Jit ``fn``, time compilation (lower + compile, with ``compiler_options``) and then
    steady-state calls; with ``hlo_lines`` count the optimised program's lines too.

    Returns the :class:`Timing` and the output of one call (for correctness checks)."""
    import jax

    jitted = jax.jit(fn)
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile(compiler_options=compiler_options)
    compile_s = time.perf_counter() - t0
    call = lambda: _block(compiled(*args))
    out, _ = _timed(call)  # first execution (page faults, thread-pool warm-up)
    _, first_s = _timed(call)
    best, med, reps, number = _measure(
        call, first_s, repeats=repeats, min_time=min_time, max_time=max_time
    )
    lines = compiled.as_text().count("\n") if hlo_lines else None
    return Timing(best, med, reps, number, compile_s, lines), out


def time_callable(
    fn: Callable[[], Any],
    *,
    repeats: int = 7,
    min_time: float = 0.05,
    max_time: float = 10.0,
    sync: Callable[[Any], Any] | None = None,
) -> tuple[Timing, Any]:
    """Time an eager callable (e.g. torch); ``sync`` waits for its result if needed (by
    default: queued CUDA work when torch runs on a GPU)."""
    sync = sync or _torch_sync
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


def package_version(dist: str) -> str:
    """An installed distribution's version, else (a source checkout on ``PYTHONPATH``) its
    module's ``__version__``, else ``?``."""
    try:
        from importlib.metadata import version

        return version(dist)
    except Exception:  # noqa: BLE001 - informative only
        mod = sys.modules.get(dist.replace("-", "_"))
        return str(getattr(mod, "__version__", "?"))


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
    if name == "pypose":  # a torch peer: on torch_device(), factory calls included
        ver = f"{ver} on {set_torch_device()}"
    return Peer(name, mod, ver)


def environment() -> str:
    """One line describing the machine and library versions (and the accelerator, when
    jax runs on one)."""
    import jax

    backend = jax.default_backend()
    if backend != "cpu":
        backend += f": {jax.devices()[0].device_kind}"
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
        f"Python {platform.python_version()}, jax {jax.__version__} ({backend})"
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
    """``a / b`` as ``12.3x`` (``0.05x`` below 0.1, ``0.97x`` near 1); '—' if either is
    missing."""
    if a is None or b is None or b == 0:
        return "—"
    r = a / b
    if r < 0.1 or 0.9 <= r < 1.1:
        # two decimals: a ratio never prints as 0.0x, and one near a 1x bar shows its side
        return f"{r:.2f}x"
    return f"{r:.1f}x" if r < 100 else f"{r:.0f}x"


def fmt_seconds(s: float | None) -> str:
    if s is None:
        return "—"
    if s < 0.01:  # two significant figures where whole milliseconds would read 0 or 1
        return f"{s * 1e3:.2f} ms"
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
