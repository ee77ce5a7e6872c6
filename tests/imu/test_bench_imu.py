"""Smoke test for bench/imu.py at tiny sizes (one task, one workload; every task runs in
``python bench/imu.py --quick``): it runs end to end and reports the timing and the
agreement table (PyPose / GTSAM columns filled when installed, skipped otherwise)."""

import re

import pytest

imu_bench = pytest.importorskip("bench.imu")


def test_bench_imu_runs_and_agrees(tmp_path):
    out = tmp_path / "imu.md"
    text = imu_bench.main(["--quick", "--windows", "4", "--samples", "20", "--tasks", "1",
                           "--workloads", "windows", "--threads", "0", "--out", str(out)])
    assert out.read_text().strip() == text.strip()
    assert text.count(f"| {imu_bench.TASKS[0]} |") == 1
    assert "## Agreement" in text
    row = [ln for ln in text.splitlines() if re.match(r"\| [\d.e+-]+ \|", ln)]
    if imu_bench.import_peer("pypose").available:
        assert "Bar: " in text
        dp = float(row[0].split("|")[1])
        assert dp < 1e-12
    if imu_bench.import_peer("gtsam").available:
        assert float(row[0].split("|")[2]) < 1e-12
