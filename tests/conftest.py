"""Session set-up shared by every test directory.

* float64 is enabled for the session; tests pass dtypes explicitly to cover float32.
* The repository root is importable (``bench``, ``notebooks/_examples``).
* XLA compilation dominates this suite on CPU, so the whole run (and every subprocess it
  starts: notebook kernels, the CLI, benchmark smoke runs) uses XLA:CPU's fast-compile
  options — about half the compile time (and one code-generation thread per compilation:
  about a quarter less CPU time); results agree with the default optimisation level to
  rounding. ``JAXPOSE_TEST_XLA_DEFAULT=1`` keeps the environment's flags unchanged.
* Markers: ``slow`` (deselected by the default command: long tests, and the in-process tests
  listed in tests/extended_tier.txt, whose lines the default tier covers), ``integration``
  (set here on every test of a module that drives a subprocess: notebooks, docs build, CLI,
  benchmark smoke runs; ``-m "not integration"`` gives the in-process unit tests alone),
  ``peer``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import pytest

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

_OPT_FLAGS = (
    "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true "
    "--xla_cpu_use_fusion_emitters=false"
)
# split_count=1 compiles each module's LLVM IR as one piece instead of splitting it for
# parallel code generation: the suite's workers already use every core, and the split costs
# about 30 % more CPU time per compilation (measured; it does not change the code's math).
FAST_COMPILE_FLAGS = f"{_OPT_FLAGS} --xla_cpu_parallel_codegen_split_count=1"

# modules whose tests start subprocesses (marked ``integration``)
INTEGRATION_MODULES = {
    "test_notebooks.py",
    "test_docs.py",
    "test_cli.py",
    "test_cli_errors.py",
    "test_bench_smoke.py",
    "test_bench_imu.py",
    "test_mjx.py",
    "test_sharding.py",
}


def _fast_compile_flags() -> str:
    """The environment's XLA_FLAGS plus the fast-compile options this XLA accepts (an unknown
    flag aborts the process, so probe in a subprocess: all of them, else the older set)."""
    base = os.environ.get("XLA_FLAGS", "")
    for extra in (FAST_COMPILE_FLAGS, _OPT_FLAGS):
        flags = f"{base} {extra}".strip()
        probe = subprocess.run(
            [sys.executable, "-c", "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"],
            env={**os.environ, "XLA_FLAGS": flags},
            capture_output=True,
            timeout=120,
        )
        if probe.returncode == 0:
            return flags
    return base


def pytest_configure(config: pytest.Config) -> None:
    # Runs in the controller before xdist starts its workers, which inherit the
    # environment; XLA reads XLA_FLAGS when the backend first initialises (after this).
    is_worker = hasattr(config, "workerinput")
    if not is_worker and not os.environ.get("JAXPOSE_TEST_XLA_DEFAULT"):
        if _OPT_FLAGS not in os.environ.get("XLA_FLAGS", ""):
            os.environ["XLA_FLAGS"] = _fast_compile_flags()


def work_unit(item: pytest.Item) -> str:
    """The xdist work unit of a test (``--dist loadgroup``): its file, so the tests of a
    module share one worker's compiled functions — except the notebooks, one unit each (a
    kernel per notebook shares nothing)."""
    unit = item.path.relative_to(ROOT).as_posix()
    if item.path.name == "test_notebooks.py" and item.name.startswith("test_notebook_executes"):
        unit += ":" + item.callspec.id  # xdist reads "name]" as no group: keep brackets out
    return unit


def _extended_tier() -> set[str]:
    """Node ids of tests/extended_tier.txt: in-process tests whose lines of ``jaxpose/`` and
    whose test function the default tier already covers (chosen by tests/_tiers.py from a
    coverage run); marked ``slow``, so ``-m slow`` runs them."""
    path = Path(__file__).with_name("extended_tier.txt")
    if not path.exists() or os.environ.get("JAXPOSE_ALL_TIERS"):  # tests/_tiers.py's run
        return set()
    text = path.read_text(encoding="utf-8").splitlines()
    return {line for line in text if line and not line.startswith("#")}


def _unit_costs() -> dict[str, float]:
    path = Path(__file__).with_name("durations.json")
    return json.loads(path.read_text(encoding="utf-8")) if path.exists() else {}


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    costs = _unit_costs()
    default = sorted(costs.values())[len(costs) // 2] if costs else 0.0
    extended = _extended_tier()
    for item in items:
        if item.path.name in INTEGRATION_MODULES:
            item.add_marker(pytest.mark.integration)
        if item.nodeid in extended:
            item.add_marker(pytest.mark.slow)
        item.add_marker(pytest.mark.xdist_group(work_unit(item)))
    # Longest units first (with --no-loadscope-reorder xdist hands them out in this order),
    # so no long unit starts last and leaves one worker busy alone at the end.
    order = {unit: i for i, unit in enumerate(dict.fromkeys(map(work_unit, items)))}
    items.sort(key=lambda it: (-costs.get(work_unit(it), default), order[work_unit(it)]))


# ``JAXPOSE_WRITE_DURATIONS=1 python -m pytest -n auto -m "not slow"`` refreshes
# tests/durations.json (seconds per work unit, summed over setup, call and teardown).
_measured: dict[str, float] = {}


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if os.environ.get("JAXPOSE_WRITE_DURATIONS"):
        nodeid = report.nodeid
        at = nodeid.rfind("@")
        unit = nodeid[at + 1 :] if at > nodeid.rfind("]") else nodeid.split("::")[0]
        _measured[unit] = _measured.get(unit, 0.0) + report.duration


def pytest_sessionfinish(session: pytest.Session) -> None:
    if os.environ.get("JAXPOSE_WRITE_DURATIONS") and not hasattr(session.config, "workerinput"):
        costs = {k: round(v, 1) for k, v in sorted(_measured.items(), key=lambda kv: -kv[1])}
        path = Path(__file__).with_name("durations.json")
        path.write_text(json.dumps(costs, indent=1) + "\n", encoding="utf-8")
