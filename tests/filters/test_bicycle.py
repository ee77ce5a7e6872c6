"""Bicycle benchmark (notebooks/_examples/bicycle_filters.py): EKF, UKF and PF over
Monte-Carlo runs — NEES consistency and RMSE. Smoke size by default, 100 runs when slow."""

import numpy as np
import pytest

from notebooks._examples import bicycle_filters as bf


def test_bicycle_filters_smoke():
    # EKF and PF only (UKF has the EKF's code path here; the slow test runs all three):
    # compilation dominates this smoke run.
    mc = bf.monte_carlo(runs=4, steps=15, num_particles=100, filters=("EKF", "PF"))
    stats = bf.summary(mc)
    assert set(stats) == {"EKF", "PF"}
    for name, s in stats.items():
        assert np.isfinite(s["rmse_pos"]) and s["rmse_pos"] < 1.0, name
        assert np.isfinite(s["anees"]), name
    assert 0.5 < stats["EKF"]["anees"] < 20  # 100 particles: too few for a PF NEES
    assert "ANEES" in bf.format_summary(stats, 4)
    lo, hi = bf.chi2_band(4, 100)
    assert 3.4 < lo < 3.5 and 4.5 < hi < 4.6  # χ² quantiles (400 dof) / 100


@pytest.mark.slow
def test_bicycle_monte_carlo_consistency():
    mc = bf.monte_carlo(runs=100, steps=100, num_particles=1000)
    stats = bf.summary(mc)
    print("\n" + bf.format_summary(stats, 100))
    lo, hi = bf.chi2_band(4, 100)
    for name in ("EKF", "UKF"):
        s = stats[name]
        assert lo <= s["anees"] <= hi, f"{name} ANEES {s['anees']:.2f} outside [{lo:.2f}, {hi:.2f}]"
        assert s["in_band"] >= 0.8, f"{name}: only {s['in_band']:.0%} of steps in the band"
    # The PF's sample covariance is slightly optimistic at 1000 particles; bound it loosely.
    assert stats["PF"]["anees"] < 1.5 * 4
    assert stats["PF"]["rmse_pos"] < 1.25 * stats["EKF"]["rmse_pos"]
