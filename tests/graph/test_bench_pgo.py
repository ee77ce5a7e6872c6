"""bench/pgo.py runs end to end (so the benchmark never rots); a missing peer is reported
as skipped, never faked."""

from __future__ import annotations

import re

import pytest

from .conftest import data_file

pgo_bench = pytest.importorskip("bench.pgo")


def _rows(text: str) -> dict[str, list[str]]:
    out = {}
    for line in text.split("Time per iteration")[0].splitlines():  # the first table
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) > 5 and cells[0] not in ("file", "") and not cells[0].startswith("-"):
            out[cells[0]] = cells
    return out


def test_disabled_or_missing_contestants_are_reported_as_skipped(monkeypatch):
    monkeypatch.setenv("JAXPOSE_BENCH_SKIP", "gtsam")
    text = pgo_bench.main(["--files", "tinyGrid3D,surely_missing_file", "--contestants",
                           "gtsam"])
    rows = _rows(text)
    assert "disabled by JAXPOSE_BENCH_SKIP" in rows["tinyGrid3D"][6]
    assert "not selected" in rows["tinyGrid3D"][2]
    assert "not found" in rows["surely_missing_file"][2]
    assert re.search(r"load average \(1/5/15 min\) [\d.]+ [\d.]+ [\d.]+", text)


@pytest.mark.slow
def test_tinygrid3d_runs_and_costs_agree():
    data_file("tinyGrid3D.g2o")
    text = pgo_bench.main(["--files", "tinyGrid3D", "--repeats", "1"])
    row = _rows(text)["tinyGrid3D"]
    assert row[1] == "9 / 11" and row[14] == "converged"
    # the default jaxpose pgo path (init auto): a graph this small starts in the solve
    assert row[2] == "chordal, in the solve"
    assert abs(float(row[10]) - 9.313909) < 1e-6
    if "skipped" not in row[6]:  # GTSAM installed: same cost from both of its paths
        assert abs(float(row[13])) < 1e-8
        assert abs(float(row[12]) - 9.313909) < 1e-6
        assert row[8].endswith("x")
    assert "cost vs README" in text and "pass" in text.split("## The issue's bar")[1]
    assert "Result: bar" in text and "per graph: tinyGrid3D" in text
