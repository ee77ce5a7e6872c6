"""jaxpose.Results: the one status vocabulary (codes, messages, text for batched arrays)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpose as jp
from jaxpose import Results


def test_codes_are_the_stored_integers():
    # stored int32 status arrays keep their meaning across the library
    assert [(m.name, int(m)) for m in Results] == [
        ("RUNNING", -1), ("CONVERGED", 0), ("MAX_STEPS", 1), ("DIVERGED", 2),
        ("NON_FINITE", 3), ("DEGENERATE", 4),
    ]
    assert all(isinstance(m.message, str) and m.message and "\n" not in m.message
               for m in Results)
    assert len({m.message for m in Results}) == len(Results)
    status = jnp.array([0, 3], jnp.int32)
    np.testing.assert_array_equal(status == Results.NON_FINITE, [False, True])


def test_name_and_message_of_scalars_and_batches():
    assert Results.name_of(0) == "converged"
    assert Results.name_of(np.int32(3)) == "non_finite"
    assert Results.message_of(jnp.asarray(4)) == Results.DEGENERATE.message
    batch = jnp.array([[0, 1], [2, 4]], jnp.int32)
    names = Results.name_of(batch)
    assert names.shape == (2, 2)
    assert names.tolist() == [["converged", "max_steps"], ["diverged", "degenerate"]]
    msgs = Results.message_of(batch)
    assert msgs[1, 0] == Results.DIVERGED.message
    assert Results.name_of(np.zeros((0,), np.int32)).shape == (0,)


def test_bad_status_raises_naming_the_argument():
    with pytest.raises(ValueError, match=r"status: unknown result code\(s\) \[7\]"):
        Results.name_of(np.array([0, 7]))
    with pytest.raises(TypeError, match="status: expected integer"):
        Results.name_of(np.array([0.5]))
    for bad in (float("inf"), float("nan")):  # inf was a raw OverflowError from int()
        with pytest.raises(TypeError, match="status: expected integer"):
            Results.name_of(bad)
    with pytest.raises(TypeError, match="status: expected a concrete"):
        jax.jit(lambda s: Results.name_of(s))(jnp.int32(0))


def test_solvers_report_the_shared_codes():
    """least_squares, graph solves and control solutions speak the same vocabulary."""
    sol = jp.optim.least_squares(lambda x, a: x - a, jnp.zeros(2), jnp.ones(2))
    assert int(sol.status) == Results.CONVERGED and sol.status_name == "converged"
    capped = jp.optim.least_squares(lambda x, a: jnp.exp(x) - a, jnp.zeros(2), 5 * jnp.ones(2),
                                    max_steps=1)
    assert capped.status_name == "max_steps"
    batched = jax.vmap(lambda a: jp.optim.least_squares(lambda x, b: x - b, jnp.zeros(1), a))(
        jnp.ones((3, 1)))
    assert batched.status_name.tolist() == ["converged"] * 3


def test_a_bool_mask_is_not_a_status():
    """``status == Results.CONVERGED`` (a mask) was read as codes 1/0: converged problems
    were labelled 'max_steps' and the others 'converged'."""
    mask = np.array([0, 1]) == int(Results.CONVERGED)
    for lookup in (Results.name_of, Results.message_of):
        with pytest.raises(TypeError, match="got a bool array"):
            lookup(mask)
