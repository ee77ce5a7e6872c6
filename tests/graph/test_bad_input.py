"""Bad input to factors and graphs: clear exceptions naming the argument (raised eagerly,
before anything is traced or compiled)."""

from __future__ import annotations

import re

import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.graph import Factor, FactorGraph, between_residual, default_stopping, solve
from jaxpose.lie import SE3

from .conftest import random_poses


def _poses(n: int = 4) -> SE3:
    return SE3(jnp.asarray(random_poses(np.random.default_rng(0), "SE3", n)))


def _between(i, j, info=None, name="between"):
    z = SE3(jnp.asarray(random_poses(np.random.default_rng(1), "SE3", len(i))))
    return Factor(between_residual, [("pose", np.asarray(i)), ("pose", np.asarray(j))],
                  data=z, information=info, name=name)


def test_mismatched_index_lengths():
    with pytest.raises(ValueError, match=r"variables\[1\].*3 indices, but slot 0 has 2"):
        Factor(between_residual, [("pose", np.array([0, 1])), ("pose", np.array([1, 2, 3]))])


def test_data_with_wrong_leading_axis():
    z = SE3(jnp.asarray(random_poses(np.random.default_rng(1), "SE3", 3)))
    with pytest.raises(ValueError, match=r"Factor\(data\).*leading axis 2"):
        Factor(between_residual, [("pose", [0, 1]), ("pose", [1, 2])], data=z)


def test_bad_indices_and_slots():
    with pytest.raises(ValueError, match=r"1-D integer array"):
        Factor(between_residual, [("pose", np.array([0.0, 1.0]))])
    with pytest.raises(TypeError, match=r"\(type_name, indices\) pair"):
        Factor(between_residual, [(0, np.array([0, 1]))])
    with pytest.raises(TypeError, match="callable"):
        Factor("between", [("pose", [0])])


def test_non_spd_information():
    info = np.tile(np.eye(6), (2, 1, 1))
    info[1, 5, 5] = -1.0
    with pytest.raises(ValueError, match="factor 1 has an information matrix that is not "
                                         "positive definite"):
        _between([0, 1], [1, 2], info)
    asym = np.eye(6)
    asym[0, 1] = 0.5
    with pytest.raises(ValueError, match="non-symmetric"):
        _between([0, 1], [1, 2], asym)
    nan = np.eye(6)
    nan[2, 2] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        _between([0, 1], [1, 2], nan)
    with pytest.raises(ValueError, match=r"expected shape \(2, r, r\) or \(r, r\)"):
        _between([0, 1], [1, 2], np.eye(6)[None].repeat(3, 0))


def test_unknown_variable_type():
    with pytest.raises(KeyError, match=r"factor 'odo' uses variable type 'pose'.*\['point'\]"):
        FactorGraph([_between([0], [1], name="odo")], {"point": jnp.zeros((3, 3))})


def test_out_of_range_indices():
    with pytest.raises(IndexError, match=r"references 'pose' index 4, but only 4 variables"):
        FactorGraph([_between([0, 1], [1, 4])], {"pose": _poses(4)})
    with pytest.raises(IndexError, match=r"references 'pose' index -1"):
        FactorGraph([_between([0, -1], [1, 2])], {"pose": _poses(4)})


def test_fixed_index_out_of_range_or_unknown_type():
    with pytest.raises(IndexError, match=r"fixed\['pose'\].*out of range for 4 variables"):
        FactorGraph([_between([0], [1])], {"pose": _poses(4)}, fixed={"pose": [4]})
    with pytest.raises(KeyError, match="fixed.*unknown variable type 'landmark'"):
        FactorGraph([_between([0], [1])], {"pose": _poses(4)}, fixed={"landmark": [0]})


def test_bad_graph_arguments():
    with pytest.raises(ValueError, match="at least one Factor"):
        FactorGraph([], {"pose": _poses()})
    with pytest.raises(TypeError, match=r"factors\[0\]\): expected Factor"):
        FactorGraph([lambda x: x], {"pose": _poses()})
    with pytest.raises(ValueError, match=r"variables\['pose'\].*batch of shape \(n,\)"):
        FactorGraph([_between([0], [1])], {"pose": SE3(jnp.zeros((2, 2, 7)))})
    with pytest.raises(ValueError, match=r"variables\['point'\].*array \(n, d\)"):
        FactorGraph([_between([0], [1])], {"pose": _poses(), "point": jnp.zeros(3)})
    graph = FactorGraph([_between([0], [1])], {"pose": _poses()})
    with pytest.raises(ValueError, match="linear_solver='cholmod'"):
        solve(graph, linear_solver="cholmod")


def _nan_away(x, z):
    """Finite only at the start value z (every trial step lands on NaN)."""
    return jnp.where(x == z, x - 3.0, jnp.nan)


def test_all_nan_trials_end_non_finite_not_max_steps():
    """max_steps below the reject budget (64) with every trial NaN: ``non_finite`` (the
    status used to be ``max_steps``); the initial variables are kept."""
    x0 = jnp.array([[1.0], [2.0]])
    fac = Factor(_nan_away, [("x", np.array([0, 1]))], data=x0)
    graph = FactorGraph([fac], {"x": x0})
    sol = solve(graph, stopping=default_stopping(5), linear_solver="dense")
    assert sol.status_name == "non_finite" and int(sol.iterations) == 5
    np.testing.assert_array_equal(sol.variables["x"], x0)
    # a Jacobian that is not finite at the start: non_finite at once, as least_squares
    sq = Factor(lambda x, z: jnp.sqrt(x) + z, [("x", np.array([0]))], data=jnp.ones((1, 1)))
    sol = solve(FactorGraph([sq], {"x": jnp.zeros((1, 1))}), linear_solver="dense")
    assert sol.status_name == "non_finite" and int(sol.iterations) == 0


def test_file_containers_refuse_traced_data_naming_the_differentiable_path():
    """``BALProblem`` and ``PoseGraph`` hold NumPy data: built inside ``grad`` they raise a
    TypeError naming the field and the way to differentiate (the factor graph's data),
    not a TracerArrayConversionError from deep inside NumPy."""
    import jax

    from jaxpose.datasets import synthetic_bal, synthetic_pose_graph
    from jaxpose.io import BALProblem, PoseGraph

    prob, _ = synthetic_bal(4, 10, 3, seed=0)
    graph, _ = synthetic_pose_graph("SE2", n_poses=6, seed=0)

    def bal(obs):
        BALProblem(prob.cameras, prob.points, prob.camera_index, prob.point_index, obs)
        return jnp.sum(obs)

    def pose_graph(z):
        PoseGraph(graph.kind, graph.vertex_ids, graph.poses, graph.edges, z, graph.information)
        return jnp.sum(z)

    with pytest.raises(TypeError, match=r"BALProblem\.observations: got a traced array.*"
                                        r"bundle_adjustment_problem.*tree_at"):
        jax.grad(bal)(jnp.asarray(prob.observations))
    with pytest.raises(TypeError, match=r"PoseGraph\.measurements: got a traced array"):
        jax.jit(pose_graph)(jnp.asarray(graph.measurements))


def test_information_must_match_the_residual_dimension():
    # a 3 × 3 information on a 6-dimensional residual used to whiten only its first three
    # components (the translation): a cost without the rotation, silently
    for info in (np.eye(3), np.tile(np.eye(1), (2, 1, 1))):
        with pytest.raises(ValueError, match=r"6-dimensional residuals but (3 × 3|1 × 1) "
                                             r"information.*\(2, 6, 6\) or \(6, 6\)"):
            FactorGraph([_between([0, 1], [1, 2], info)], {"pose": _poses()})
    FactorGraph([_between([0, 1], [1, 2], np.eye(6))], {"pose": _poses()})


def test_variables_of_another_shape_are_refused_everywhere():
    # the factors' index gathers clamp: 2 of 4 poses gave a cost, a linearisation, marginals
    # and deletion statistics of the wrong poses, without an error
    import jax

    from jaxpose.graph import cost, deletion_statistics, gnc, linearize, marginals
    from jaxpose.lie import SO3

    graph = FactorGraph([_between([0, 1, 2], [1, 2, 3])], {"pose": _poses()},
                        fixed={"pose": [0]})
    short = {"pose": _poses(2)}
    calls = {"cost(variables)": lambda v: cost(graph, v),
             "linearize(variables)": lambda v: linearize(graph, v),
             "solve(variables)": lambda v: solve(graph, v),
             "marginals(solution)": lambda v: marginals(graph, v),
             "deletion_statistics(values)": lambda v: deletion_statistics(graph, v),
             "gnc(variables)": lambda v: gnc(graph, v)}
    for name, call in calls.items():
        with pytest.raises(ValueError, match=re.escape(name) + r": variables\['pose'\]: "
                           r"expected SE3 of batch shape \(4,\).*got SE3 of batch shape \(2,\)"):
            call(short)
    with pytest.raises(ValueError, match=r"got SO3 of batch shape \(4,\)"):
        cost(graph, {"pose": SO3.identity((4,))})
    with pytest.raises(ValueError, match=r"got array of shape \(4, 7\)"):
        cost(graph, {"pose": jnp.zeros((4, 7))})
    with pytest.raises(ValueError, match=r"variable types \['pose'\], got \['point'\]"):
        cost(graph, {"point": _poses()})
    with pytest.raises(ValueError, match=r"solve\(variables\)"):  # also under jit
        jax.jit(solve)(graph, short)
    assert np.isfinite(float(cost(graph, graph.variables)))


def test_fixed_indices_must_be_integers():
    # a boolean mask was cast to indices (True → 1, False → 0: poses 0 and 1 fixed), floats
    # truncated
    mask = np.array([True, False, False, False])
    for fixed, dtype in ((mask, "bool.*np.flatnonzero"), ([2.9], "float64")):
        with pytest.raises(ValueError, match=r"fixed\['pose'\]\): expected integer indices, "
                                             r"got dtype " + dtype):
            FactorGraph([_between([0], [1])], {"pose": _poses()}, fixed={"pose": fixed})
    graph = FactorGraph([_between([0], [1])], {"pose": _poses()}, fixed={"pose": []})
    assert graph.structure.fixed_counts == (0,)

    from jaxpose import synthetic_bal
    from jaxpose.graph import bundle_adjustment_problem

    bal, _ = synthetic_bal(n_cameras=3, n_points=10, obs_per_point=2, seed=0)
    with pytest.raises(ValueError, match=r"fixed_cameras\): expected integer indices"):
        bundle_adjustment_problem(bal, fixed_cameras=[1.7])


def test_pose_graph_cost_and_rmse_refuse_what_they_cannot_evaluate():
    from jaxpose import synthetic_bal, synthetic_pose_graph
    from jaxpose.graph import pose_graph_cost, reprojection_rmse
    from jaxpose.io import BALProblem

    g, _ = synthetic_pose_graph("SE3", n_poses=8, seed=1)
    for poses in (np.vstack([g.poses, g.poses]), g.poses[:3], g.poses[:, :4]):
        with pytest.raises(ValueError, match=r"pose_graph_cost\(poses\): expected shape "
                                             r"\(8, 7\)"):
            pose_graph_cost(g, poses)
    bal, _ = synthetic_bal(n_cameras=2, n_points=3, obs_per_point=2, seed=0)
    empty = BALProblem(bal.cameras, bal.points, bal.camera_index[:0], bal.point_index[:0],
                       bal.observations[:0])
    with pytest.raises(ValueError, match="no observations"):
        reprojection_rmse(empty)


def test_traced_kernel_parameter_outside_its_domain_raises_in_solve():
    # a learned Huber scale that became negative gave a negative cost silently
    import jax

    from jaxpose.optim import Huber

    def solved_cost(delta):
        f = Factor(between_residual, [("pose", np.array([0, 1])), ("pose", np.array([1, 2]))],
                   data=SE3(jnp.asarray(random_poses(np.random.default_rng(1), "SE3", 2))),
                   kernel=Huber(delta))
        return solve(FactorGraph([f], {"pose": _poses(3)}, fixed={"pose": [0]})).cost

    msg = r"Huber\(delta\): delta has to be positive"
    with pytest.raises(Exception, match=msg):  # the user's jax.jit: in the runtime error
        jax.block_until_ready(jax.jit(solved_cost)(jnp.asarray(-0.5)))
    with pytest.raises(Exception, match=msg):  # eager grad: a traced δ inside solve
        jax.grad(solved_cost)(jnp.asarray(-0.5))
    with pytest.raises(ValueError, match=r"Huber\(delta=array\(-0.5\)\)"):  # concrete
        solved_cost(jnp.asarray(-0.5))
    assert float(jax.jit(solved_cost)(jnp.asarray(0.5))) >= 0.0
    assert np.isfinite(float(jax.grad(solved_cost)(jnp.asarray(0.5))))
    # marginals and deletion statistics linearise through the same kernels
    from jaxpose.graph import deletion_statistics, marginals

    def graph(delta):
        f = Factor(between_residual, [("pose", np.array([0, 1, 0])),
                                      ("pose", np.array([1, 2, 2]))],
                   data=SE3(jnp.asarray(random_poses(np.random.default_rng(1), "SE3", 3))),
                   kernel=Huber(delta))
        return FactorGraph([f], {"pose": _poses(3)}, fixed={"pose": [0]})

    for fn in (lambda d: marginals(graph(d)).covariances["pose"],
               lambda d: deletion_statistics(graph(d), method="dense")[0]):
        assert np.all(np.isfinite(np.asarray(jax.jit(fn)(jnp.asarray(0.5)))))
        with pytest.raises(Exception, match=msg):
            jax.block_until_ready(jax.jit(fn)(jnp.asarray(-0.5)))


def test_graph_cost_checks_kernel_parameters():
    # graph.cost evaluated a learned Huber scale that became negative without a check:
    # a negative cost, silently (solve, marginals and deletion statistics checked it)
    import equinox as eqx
    import jax

    from jaxpose.graph import cost
    from jaxpose.optim import Huber

    def graph(delta):
        f = Factor(between_residual, [("pose", np.array([0, 1])), ("pose", np.array([1, 2]))],
                   data=SE3(jnp.asarray(random_poses(np.random.default_rng(1), "SE3", 2))),
                   kernel=Huber(delta))
        return FactorGraph([f], {"pose": _poses(3)}, fixed={"pose": [0]})

    def at(delta):
        g = graph(delta)
        return cost(g, g.variables)

    assert float(jax.jit(at)(jnp.asarray(0.5))) > 0.0
    with pytest.raises(Exception, match=r"Huber\(delta\): delta has to be positive"):
        jax.block_until_ready(jax.jit(at)(jnp.asarray(-0.5)))
    g = eqx.tree_at(lambda g: g.factors[0].kernel.delta, graph(0.5), -0.5)  # no constructor
    with pytest.raises(ValueError, match=r"Huber\(delta=-0.5\)"):
        cost(g, g.variables)


# Found by an audit (session 48)
def test_pcg_tolerance_zero_is_refused_and_solve_pcg_does_not_stop_early():
    """rtol = 0 made the CG's absolute tolerance 0, so lineax's test was 0/0 = NaN on every
    zero entry of the right-hand side (fixed variables always give some) and read as
    converged after one iteration: the step was not the Newton step."""
    import jax

    from jaxpose.graph import PCG, marginals
    from jaxpose.graph import _linear as linear

    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match=r"PCG\(rtol\)=.*: expected a positive tolerance"):
            PCG(rtol=bad)
    a = jnp.array([[4.0, 1.0, 0.0], [1.0, 3.0, 0.0], [0.0, 0.0, 1.0]])
    b = jnp.array([1.0, 2.0, 0.0])
    x, _ = jax.jit(lambda b: linear.solve_pcg(lambda v: a @ v, b, lambda v: v, rtol=0.0,
                                              max_iters=50))(b)
    np.testing.assert_allclose(x, np.linalg.solve(np.asarray(a), np.asarray(b)), atol=1e-12)
    graph = FactorGraph([_between([0, 1], [1, 2])], {"pose": _poses(3)}, fixed={"pose": [0]})
    for name, value in (("cg_rtol", 0.0), ("cg_max_iters", 0), ("batch_size", -3)):
        with pytest.raises(ValueError, match=rf"marginals\({name}"):
            marginals(graph, method="pcg", **{name: value})


def test_gnc_tolerances_and_gnc_options_without_gnc():
    """A negative or NaN GNC tolerance switched its stopping test off (40 outer iterations
    and MAX_STEPS where 8 converge); gnc_options without robust='gnc' were ignored, even a
    misspelt one."""
    from jaxpose.datasets import synthetic_pose_graph
    from jaxpose.graph import gnc, optimize_pose_graph, pose_graph_problem

    pg, _ = synthetic_pose_graph("SE2", n_poses=5, noise=(0.01, 0.01), seed=0)
    problem = pose_graph_problem(pg)
    for name in ("cost_rtol", "weights_tol"):
        for bad in (-1.0, float("nan")):
            with pytest.raises(ValueError, match=rf"gnc\({name}=.*expected a tolerance >= 0"):
                gnc(problem, **{name: bad})
    with pytest.raises(ValueError, match=r"gnc_options\): used by robust='gnc' only"):
        optimize_pose_graph(pg, gnc_options={"surogate": "gm"})


def test_optimize_bal_takes_a_graph_linear_solver_object():
    """GraphLinearSolver("schur") was compared with the string "schur": no points were
    eliminated and the solve asked the caller to rebuild a graph it never built."""
    from jaxpose.datasets import synthetic_bal
    from jaxpose.graph import GraphLinearSolver, optimize_bal

    prob, _ = synthetic_bal(6, 30, seed=0)
    a = optimize_bal(prob, linear_solver=GraphLinearSolver("schur"), fixed_cameras=[0, 1])[1]
    b = optimize_bal(prob, linear_solver="schur", fixed_cameras=[0, 1])[1]
    assert a.status_name == "converged"
    np.testing.assert_allclose(float(a.cost), float(b.cost), rtol=1e-12)


def test_an_empty_variable_type_is_refused_by_name():
    """An empty batch of variables raised a bare KeyError: 0 from the sparsity pattern (or,
    unused, numpy's "need at least one array to stack" from marginals)."""
    used = Factor(lambda x, z: x - z, [("x", np.zeros(0, int))], data=jnp.zeros((0, 2)))
    with pytest.raises(ValueError, match=r"FactorGraph\(variables\['x'\]\): expected at least "
                                         r"one variable, got an empty batch"):
        FactorGraph([used], {"x": jnp.zeros((0, 2))})
    f = Factor(lambda x, z: x - z, [("x", np.array([0, 1]))], data=jnp.ones((2, 2)))
    with pytest.raises(ValueError, match=r"FactorGraph\(variables\['y'\]\)"):
        FactorGraph([f], {"x": jnp.zeros((2, 2)), "y": SE3.identity((0,))})


def test_integer_starting_values_are_promoted_like_least_squares():
    """An integer start for an array variable ended in a raw while_loop carry TypeError
    (int vs float); optim.least_squares already promotes integers to the default float."""
    z = np.array([[0.4, 1.6], [2.5, -0.7]])
    f = Factor(lambda x, d: x - d, [("pt", np.array([0, 1]))], data=z)
    graph = FactorGraph([f], {"pt": np.zeros((2, 2), int)})
    assert graph.variables["pt"].dtype == jnp.result_type(float)
    sol = solve(graph)
    assert sol.status_name == "converged"
    np.testing.assert_allclose(sol.variables["pt"], z, atol=1e-12)


def _chain_and_star():
    """A graph on four scalars (a prior on x0, three between factors along a chain) and
    the indices of a star from x0 with the same counts."""
    def prior(x, z):
        return x - z

    def between(xi, xj, z):
        return xj - xi - z

    pri = Factor(prior, [("x", np.array([0]))], data=jnp.zeros((1, 1)))
    chain = Factor(between, [("x", np.array([0, 1, 2])), ("x", np.array([1, 2, 3]))],
                   data=jnp.ones((3, 1)))
    graph = FactorGraph([pri, chain], {"x": jnp.zeros((4, 1))})
    star = (np.array([0, 0, 0], np.int32), np.array([1, 2, 3], np.int32))
    return graph, star


def test_indices_replaced_after_construction_are_refused():
    """The structure (H's pattern) is built from the indices once: with a chain's indices
    replaced by a star's (eqx.tree_at), marginals came out [1, 2, 3, 4] (the chain's)
    where the star's are [1, 2, 2, 2], and a solve with gtol 1e-4 said converged with an
    implicit gradient of [6, 10, 12] where [2, 2, 2] is right. Now solve, marginals, gnc
    and deletion_statistics raise, eagerly and with the graph traced under jit."""
    import equinox as eqx
    import jax

    from jaxpose.graph import deletion_statistics, gnc, marginals

    graph, star = _chain_and_star()
    stale = eqx.tree_at(lambda g: g.factors[1].indices, graph, star)
    match = r"indices differ from those the FactorGraph's structure .* was built from"
    for call in (lambda g: solve(g), lambda g: marginals(g, method="dense"),
                 lambda g: gnc(g), lambda g: deletion_statistics(g),
                 jax.jit(lambda g: solve(g).cost)):  # traced indices: checked at run time
        with pytest.raises(Exception, match=match):
            jax.block_until_ready(call(stale))
    assert float(jax.jit(lambda g: solve(g).cost)(graph)) < 1e-20  # the built graph runs
    rebuilt = FactorGraph([graph.factors[0], Factor(graph.factors[1].residual,
                                                     [("x", star[0]), ("x", star[1])],
                                                     data=jnp.ones((3, 1)))],
                          {"x": jnp.zeros((4, 1))})
    np.testing.assert_allclose(np.ravel(marginals(rebuilt, method="dense").covariances["x"]),
                               [1.0, 2.0, 2.0, 2.0], rtol=1e-12)


def test_variables_and_information_replaced_after_construction_are_refused():
    """Three variables put in place of four (eqx.tree_at): cost clamped the factor that
    uses x3 to x2 and returned 1.5 silently; a 1 × 1 square-root information on 2-D
    residuals weighted only the first component (cost 5 for 15)."""
    import equinox as eqx

    from jaxpose.graph import cost, marginals

    graph, _ = _chain_and_star()
    fewer = eqx.tree_at(lambda g: g.variables["x"], graph, jnp.zeros((3, 1)))
    match = r"graph.variables\['x'\] holds 3 of tangent dimension 1, but the FactorGraph " \
            r"was built with 4"
    for call in (lambda g: cost(g, g.variables), lambda g: solve(g),
                 lambda g: marginals(g, method="dense")):
        with pytest.raises(ValueError, match=match):
            call(fewer)

    def prior2(x, z):
        return x - z

    two = FactorGraph([Factor(prior2, [("x", np.arange(2))], data=jnp.ones((2, 2)),
                              information=np.eye(2))], {"x": jnp.zeros((2, 2))})
    narrow = eqx.tree_at(lambda g: g.factors[0].sqrt_info, two, jnp.ones((2, 1, 1)))
    with pytest.raises(ValueError, match=r"2-dimensional residuals but 1 × 1 information"):
        cost(narrow, narrow.variables)
