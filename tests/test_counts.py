"""Counts (iterations, horizons, sizes) share one check, ``jaxpose._checks.check_count``:
a Python or NumPy integer at or above the minimum; a bool, a float or a string is not a
count. Before it was shared, ``StopOnPlateau(steps=True)`` ran one step, and
``PCG(max_iters=np.int64(50))`` (a count read from a NumPy array) was refused."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

import jaxpose.graph as jg
import jaxpose.optim as jo
from jaxpose.control import MPC, QuadraticCost
from jaxpose.dynamics import LTI, Pendulum
from jaxpose.geometry import knn

CONSTRUCTORS = [  # (make, error name, minimum, field)
    (lambda v: jo.StopOnPlateau(steps=v), "StopOnPlateau(steps)", 1, "steps"),
    (lambda v: jo.StopOnPlateau(steps=5, patience=v), "StopOnPlateau(patience)", 1, "patience"),
    (lambda v: jo.Stopping(max_steps=v), "Stopping(max_steps)", 0, "max_steps"),
    (lambda v: jo.Stopping(max_rejects=v), "Stopping(max_rejects)", 1, "max_rejects"),
    (lambda v: jo.CG(max_steps=v), "CG(max_steps)", 1, "max_steps"),
    (lambda v: jg.PCG(max_iters=v), "PCG(max_iters)", 1, "max_iters"),
    (lambda v: jg.GraphLinearSolver(dense_max=v), "GraphLinearSolver(dense_max)", 0, "dense_max"),
    (lambda v: Pendulum(substeps=v), "substeps", 1, "substeps"),
    (lambda v: MPC(LTI(np.eye(2), np.ones((2, 1))), QuadraticCost(np.eye(3), None, np.eye(2)), v),
     "horizon", 1, "horizon"),
]


@pytest.mark.parametrize("make, name, minimum, field", CONSTRUCTORS,
                         ids=[c[1] for c in CONSTRUCTORS])
def test_counts_are_integers_at_or_above_their_minimum(make, name, minimum, field):
    pattern = re.escape(f"{name}: expected an int >= {minimum}")
    for bad in (True, 2.0, "3"):
        with pytest.raises(TypeError, match=pattern):
            make(bad)
    with pytest.raises(ValueError, match=pattern + f", got {minimum - 1}"):
        make(minimum - 1)
    for good in (minimum, np.int64(minimum + 2), np.int32(minimum + 1)):
        with warnings.catch_warnings():  # no "JAX array set as static" for a NumPy count
            warnings.simplefilter("error")
            obj = make(good)
        # stored as a Python int: static fields are hashed and compared
        assert type(getattr(obj, field)) is int and getattr(obj, field) == good


def test_a_numpy_count_works_in_a_call():
    pts = np.random.default_rng(0).normal(size=(6, 3))
    got = knn(pts, pts, k=np.int64(2))
    assert got.indices.shape == (6, 2)
    np.testing.assert_array_equal(np.asarray(got.indices)[:, 0], np.arange(6))
    with pytest.raises(TypeError, match=r"knn\(k\): expected an int >= 1, got bool"):
        knn(pts, pts, k=True)
