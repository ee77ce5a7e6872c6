"""Smoke test for bench/smoother.py: it runs end to end at the quick size and prints its
table and Result line (GTSAM's column is '—' when gtsam is missing)."""

import pytest

smoother_bench = pytest.importorskip("bench.smoother")


@pytest.mark.slow
def test_bench_smoother_quick():
    text = smoother_bench.main(["--quick", "--threads", "0"])
    assert "| window K |" in text
    assert "\n| 0 | 4 | gauss-newton |" in text and "\n| 0.5 | 4 | incremental |" in text
    assert "Result:" in text
