"""Choose the default test tier from a coverage run: the cheapest set of in-process tests
that covers every line of ``jaxpose/`` the whole in-process suite covers, and keeps a case of
every test function whose cheapest case is quick (``--fn-cap``, 0.5 s), plus every test of the
files in ``ALWAYS_DEFAULT`` (structure and regression tests); the rest is written to
``tests/extended_tier.txt`` and runs under ``-m slow`` (``tests/conftest.py`` marks it).

Subprocess-driven tests (``integration``: notebooks, docs, CLI, benchmark smoke runs) and
tests already marked ``slow`` are not candidates: the first always run, the second never
by default.

Regenerate after adding or renaming many tests (a test missing from the file runs by
default, so a stale file only costs time)::

    JAXPOSE_ALL_TIERS=1 COVERAGE_FILE=/tmp/cov/.coverage python -m pytest -n auto \
        -m "not slow and not integration" --cov=jaxpose --cov-context=test --cov-report= \
        --junitxml=/tmp/cov/junit.xml
    python tests/_tiers.py /tmp/cov/.coverage /tmp/cov/junit.xml

``JAXPOSE_ALL_TIERS=1`` keeps tests/conftest.py from marking this file's tests ``slow``:
without it the run sees only the current default tier, and the file written from it
would drop every test it lists now (they would all run by default again).

The selection is a weighted greedy set cover (gain in uncovered lines and test functions
per second of the test's measured duration) followed by a pass that drops, longest first,
every chosen test whose lines and function the others still cover.
"""

from __future__ import annotations

import argparse
import collections
import heapq
import math
import sqlite3
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

from coverage.numbits import numbits_to_nums

HERE = Path(__file__).resolve().parent
TIER_FILE = HERE / "extended_tier.txt"
# node-id prefixes kept in the default tier: structural tests, and the regression tests of
# defects that returned a wrong number or an unclear error (their lines are covered by other
# tests, but not their failure modes; ~70 tests, ~12 s on 2 cores). A new file of such tests
# is listed here.
ALWAYS_DEFAULT = (
    "tests/test_architecture.py::",
    "tests/filters/test_bad_input.py::",
    "tests/geometry/test_input_regressions.py::",
    "tests/geometry/test_kdtree_checks.py::",
    "tests/graph/test_marginals_methods.py::",
    "tests/imu/test_bad_input.py::",
    "tests/imu/test_input_regressions.py::",
    "tests/imu/test_predict_checks.py::",
    "tests/io/test_io_bad_input.py::",
    "tests/optim/test_bad_input.py::",
    "tests/smoothing/test_input_regressions.py::",
    "tests/smoothing/test_status.py::",
    "tests/test_small_linalg.py::",  # the no-LAPACK checks guard against a hang
)
HEADER = (
    "# Tests deselected from the default run (marked slow by tests/conftest.py): the default\n"
    "# tier covers their lines of jaxpose/ (and their test function, if it is quick). Made by\n"
    "# tests/_tiers.py from a coverage run; run them with  python -m pytest -m slow\n"
)


def strip_group(nodeid: str) -> str:
    """The node id without the "@group" suffix xdist's ``--dist loadgroup`` appends."""
    at = nodeid.rfind("@")
    return nodeid[:at] if at > nodeid.rfind("]") and at > nodeid.rfind("::") else nodeid


def read_coverage(path: str) -> dict[str, set[tuple[int, int]]]:
    """nodeid → {(file id, line)} from a coverage database recorded with test contexts."""
    con = sqlite3.connect(path)
    contexts = dict(con.execute("select id, context from context"))
    lines: dict[str, set[tuple[int, int]]] = collections.defaultdict(set)
    rows = con.execute("select file_id, context_id, numbits from line_bits")
    for file_id, context_id, bits in rows:
        nodeid = strip_group(contexts[context_id].rsplit("|", 1)[0])
        if nodeid:
            lines[nodeid].update((file_id, n) for n in numbits_to_nums(bits))
    return lines


def read_durations(path: str) -> dict[str, float]:
    """nodeid → seconds (setup + call + teardown) from a pytest junit xml."""
    out = {}
    for case in ET.parse(path).getroot().iter("testcase"):
        module = case.get("classname", "").split(".")
        name = case.get("name", "")
        # classname "tests.lie.test_x" or "tests.lie.test_x.TestClass"
        parts, cls = module, []
        while parts and not parts[-1].startswith("test_"):
            cls.insert(0, parts.pop())
        nodeid = "/".join(parts) + ".py::" + "::".join([*cls, name])
        out[strip_group(nodeid)] = float(case.get("time", 0.0))
    return out


def function_of(nodeid: str) -> str:
    return nodeid.split("[", 1)[0]


def select(lines: dict[str, set], cost: dict[str, float], fn_cap: float = 0.5) -> set[str]:
    """The default tier: covers ∪ lines, and every test function whose cheapest case takes
    at most ``fn_cap`` seconds, at low total cost. (A test's measured cost depends on what
    its worker compiled before it, so the tier is checked by a timed run, not this sum.)"""
    tests = sorted(cost)
    cheapest: dict[str, float] = {}
    for t in tests:
        cheapest[function_of(t)] = min(cheapest.get(function_of(t), math.inf), cost[t])
    feats = {t: lines.get(t, set()) | ({("fn", function_of(t))}
                                       if cheapest[function_of(t)] <= fn_cap else set())
             for t in tests}
    need = set().union(*feats.values())
    # structural tests read the code instead of running it (they cover no lines, so the
    # cover below would never pick them); regression tests guard failure modes, not lines
    chosen: set[str] = {t for t in tests if t.startswith(ALWAYS_DEFAULT)}
    for t in chosen:
        need -= feats[t]
    # lazy greedy: a test's gain only shrinks, so a stale heap entry is an upper bound
    heap = [(-len(feats[t]) / (cost[t] + 0.05), t) for t in tests]
    heapq.heapify(heap)
    while need and heap:
        _, t = heapq.heappop(heap)
        gain = feats[t] & need
        if not gain:
            continue
        score = -len(gain) / (cost[t] + 0.05)
        if heap and score > heap[0][0]:  # no longer the best: re-queue with its true gain
            heapq.heappush(heap, (score, t))
            continue
        chosen.add(t)
        need -= gain
    count = collections.Counter(f for t in chosen for f in feats[t])
    for t in sorted(chosen, key=lambda t: -cost[t]):
        if not t.startswith(ALWAYS_DEFAULT) and all(count[f] > 1 for f in feats[t]):
            chosen.discard(t)
            count.subtract(feats[t])
    return chosen


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("coverage", help="coverage database recorded with --cov-context=test")
    ap.add_argument("junit", help="junit xml of the same run (per-test durations)")
    ap.add_argument("--fn-cap", type=float, default=0.5,
                    help="keep a case of every test function whose cheapest case takes at most "
                         "this many seconds (default 0.5)")
    args = ap.parse_args(argv)
    lines = read_coverage(args.coverage)
    cost = read_durations(args.junit)
    chosen = select(lines, cost, args.fn_cap)
    extended = sorted(set(cost) - chosen)
    total = set().union(*lines.values())
    kept = set().union(*(lines.get(t, set()) for t in chosen))
    print(
        f"{len(cost)} in-process tests, {sum(cost.values()):.0f} s; default tier {len(chosen)} "
        f"tests, {sum(cost[t] for t in chosen):.0f} s (measured alone, with coverage); "
        f"lines {len(kept)}/{len(total)}"
    )
    TIER_FILE.write_text(HEADER + "".join(f"{t}\n" for t in extended), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
