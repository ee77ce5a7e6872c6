"""bench/ba.py runs end to end (so the benchmark never rots); a missing peer or file is
reported as skipped, never faked."""

from __future__ import annotations

import re

import pytest

from .conftest import DATA

ba_bench = pytest.importorskip("bench.ba")


def _rows(text: str) -> list[list[str]]:
    out = []
    for line in text.split("## Checks")[0].splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) > 5 and cells[0] not in ("problem", "") and not cells[0].startswith("-"):
            out.append(cells)
    return out


def test_missing_file_and_disabled_gtsam_are_reported_as_skipped(monkeypatch):
    if not (DATA / "bal" / "dubrovnik-1-1-pre.txt").is_file():
        pytest.skip("reference data not present")
    monkeypatch.setenv("JAXPOSE_BENCH_SKIP", "gtsam")
    text = ba_bench.main(["--files", "dubrovnik-1-1-pre,surely_missing", "--cameras", "0",
                          "--contestants", "gtsam", "--repeats", "1"])
    rows = _rows(text)
    assert rows[0][:3] == ["dubrovnik-1-1-pre", "1 / 1 / 1", "GTSAM"]
    assert "disabled by JAXPOSE_BENCH_SKIP" in rows[0][3]
    assert rows[1][0] == "surely_missing" and "not found" in rows[1][3]
    assert re.search(r"load average \(1/5/15 min\) [\d.]+ [\d.]+ [\d.]+", text)


@pytest.mark.slow
def test_small_synthetic_problem_schur_and_plain_agree():
    text = ba_bench.main(["--files", "", "--cameras", "6", "--points", "60", "--obs", "3",
                          "--repeats", "1", "--contestants", "jaxpose,gtsam"])
    rows = {r[2]: r for r in _rows(text)}
    schur, plain = rows["jaxpose schur"], rows["jaxpose sparse"]
    assert schur[7] == plain[7] == "converged" and schur[6] == plain[6]
    assert float(schur[8]) == pytest.approx(float(plain[8]), rel=1e-9)
    if "skipped" not in rows["GTSAM"][3]:  # GTSAM installed: same minimum
        assert float(rows["GTSAM"][8]) == pytest.approx(float(schur[8]), rel=1e-6)
    assert "noise floor" in text
    assert ("faster than the plain" in text) or ("SLOWER than the plain" in text)
