"""The jaxpose.optim machinery on the sparse path: strategies, stopping rules, kernels and
correctors; analytic between-factor Jacobians of SE3, SE2 and Sim3.

References: GTSAM's minimum of pose2example (every strategy must reach it), closed-form
kernel derivatives in numpy, ``jax.grad``/``jax.jacfwd`` of the whole graph's cost as a
function of the tangent vector (``conftest.dense_residual_fn``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose import Results, read_g2o
from jaxpose.graph import (
    PCG,
    Factor,
    FactorGraph,
    between_jacobian,
    between_residual,
    default_stopping,
    linearize,
)
from jaxpose.graph import _pgo as pgo
from jaxpose.graph import solve as graph_solve
from jaxpose.graph._problem import gradient, hessian_blocks, hessian_diagonal
from jaxpose.lie import SE2, SE3, SO2, SO3, RxSO3, Sim3
from jaxpose.optim import (
    Adaptive,
    Cauchy,
    Constant,
    Dogleg,
    Huber,
    LambdaFactor,
    Nielsen,
    StopOnPlateau,
    Stopping,
    Triggs,
    TrustRegion,
)

from .conftest import (
    FAST_COMPILE,
    GTSAM_COST,
    assemble_jacobian,
    data_file,
    dense_residual_fn,
    random_poses,
    relative_se2,
)


def _solve(problem, **options):
    options = {"linear_solver": "dense", **options}
    return jax.jit(lambda g: graph_solve(g, **options), compiler_options=FAST_COMPILE)(problem)


def test_dogleg_inexact_pcg_with_plateau_stopping_reaches_gtsam_minimum():
    """Dogleg steps from inexact-Newton CG (lineax, forcing η = min(0.1, √(‖g‖/‖g₀‖)))
    and PyPose's StopOnPlateau rule."""
    problem = pgo.pose_graph_problem(read_g2o(data_file("pose2example.txt")))
    stop = Stopping(max_steps=80, cost_rtol=0.0, gtol=0.0, xtol=0.0,
                    plateau=StopOnPlateau(steps=80, patience=2, decreasing=1e-6))
    sol = _solve(problem, strategy=Dogleg(radius=0.1), stopping=stop, verbose=True,
                 linear_solver="pcg", cg=PCG(rtol="inexact"))
    assert int(sol.linear_iterations) > 0
    assert int(sol.status) == Results.CONVERGED and sol.status_name == "converged"
    np.testing.assert_allclose(float(sol.cost), GTSAM_COST["pose2example.txt"], rtol=1e-9)
    k = int(sol.iterations)
    hist = np.asarray(sol.history)
    assert 3 < k < 80 and sol.history.shape == (80,)
    assert np.all(np.diff(hist[:k]) <= 0) and np.all(np.isnan(hist[k:]))
    # the plateau rule ended it: the last two iterations decreased by < 1e-6, the one
    # before did not
    dec = -np.diff(hist[:k])
    assert np.all(dec[-2:] < 1e-6) and dec[-3] >= 1e-6, dec


@pytest.mark.slow
@pytest.mark.parametrize("strategy", [TrustRegion(), Adaptive(damping=1e-3), Constant(1e-3),
                                      Nielsen(1e-4), LambdaFactor(1.0, factor=3.0)],
                         ids=lambda s: type(s).__name__)
@pytest.mark.parametrize("damping", ["identity", "diagonal"])
def test_every_strategy_reaches_gtsam_minimum(strategy, damping):
    problem = pgo.pose_graph_problem(read_g2o(data_file("pose2example.txt")))
    sol = _solve(problem, strategy=strategy, damping=damping, stopping=default_stopping(200))
    assert sol.status_name == "converged"
    np.testing.assert_allclose(float(sol.cost), GTSAM_COST["pose2example.txt"], rtol=1e-8)


def _se2_graph(kernel, corrector=None, seed=0):
    rng = np.random.default_rng(seed)
    poses = random_poses(rng, "SE2", 6)
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 4], [4, 5], [5, 0], [1, 4]])
    z = np.stack([relative_se2(poses[i], poses[j]) for i, j in edges])
    z[:, :2] += rng.normal(scale=[[0.3], [0.02], [0.5], [0.01], [2.0], [0.05], [0.8]],
                           size=(7, 2))
    info = np.diag([2.0, 3.0, 5.0])
    factor = Factor(between_residual, [("pose", edges[:, 0]), ("pose", edges[:, 1])],
                    data=SE2(jnp.asarray(z)), information=info, kernel=kernel,
                    corrector=corrector)
    return FactorGraph([factor], {"pose": SE2(jnp.asarray(poses))}, fixed={"pose": [0]}), info


def test_kernels_and_correctors_on_the_sparse_path():
    """Triggs with Cauchy: J̃ᵀr̃ is the exact gradient of 0.5·Σρ and J̃ᵀJ̃ is
    Jᵀ(ρ'I + 2ρ''eeᵀ)J (curvature clamped where it is negative); FastTriggs (default)
    drops the ρ'' term. A plain callable kernel equals the optim kernel object."""
    delta = 0.7
    triggs, info = _se2_graph(Cauchy(delta), Triggs(min_d=1e-6))
    fast, _ = _se2_graph(Cauchy(delta))
    plain, _ = _se2_graph(lambda s: delta**2 * jnp.log1p(s / delta**2))

    @jax.jit(compiler_options=FAST_COMPILE)
    def run(a, b, c):
        ref = dense_residual_fn(a, a.variables, [info])
        zero = jnp.zeros(a.size)

        def robust(d):
            s = jnp.sum(ref(d).reshape(-1, 3) ** 2, 1)
            return 0.5 * jnp.sum(delta**2 * jnp.log1p(s / delta**2))

        lins = [linearize(x, x.variables) for x in (a, b, c)]
        return dict(lins=lins, grads=[gradient(x, lin) for x, lin in zip((a, b, c), lins)],
                    J=jax.jacfwd(ref)(zero), e=ref(zero), g_ref=jax.grad(robust)(zero),
                    cost_ref=robust(zero), diag=hessian_diagonal(a, lins[0]),
                    blocks=hessian_blocks(a, lins[0]))

    out = run(triggs, fast, plain)
    free = np.r_[np.zeros(3), np.ones(15)]
    J = np.asarray(out["J"]) * free
    e = np.asarray(out["e"]).reshape(-1, 3)
    s = np.sum(e * e, 1)
    d1 = 1 / (1 + s / delta**2)
    d2 = -1 / (delta**2 * (1 + s / delta**2) ** 2)
    assert np.any(np.sqrt(s) > 2 * delta) and np.any(np.sqrt(s) < delta / 2)  # both regimes
    g_ref = np.asarray(out["g_ref"]) * free
    for lin, g in zip(out["lins"], out["grads"], strict=True):
        np.testing.assert_allclose(float(lin.cost), float(out["cost_ref"]), rtol=1e-12)
        np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-10 * np.abs(g_ref).max())
    # Triggs: Jᵀ(ρ'I + 2ρ''eeᵀ)J, with D = 1 + 2sρ''/ρ' clamped at min_d where the exact
    # curvature along e is not positive (documented): ρ'(D − 1)eeᵀ/s
    big_d = np.maximum(1 + 2 * s * d2 / d1, 1e-6)
    assert np.any(1 + 2 * s * d2 / d1 < 0) and np.any(1 + 2 * s * d2 / d1 > 0.5)
    H_exact = sum(J[3 * k : 3 * k + 3].T @ (d1[k] * np.eye(3) + d1[k] * (big_d[k] - 1)
                                             * np.outer(e[k], e[k]) / s[k])
                  @ J[3 * k : 3 * k + 3] for k in range(len(s)))
    H_irls = sum(d1[k] * J[3 * k : 3 * k + 3].T @ J[3 * k : 3 * k + 3] for k in range(len(s)))
    jt = assemble_jacobian(triggs, out["lins"][0].jacobians)
    np.testing.assert_allclose(jt.T @ jt, H_exact, rtol=0, atol=1e-9 * np.abs(H_exact).max())
    np.testing.assert_allclose(out["diag"], np.diag(H_exact), rtol=0,
                               atol=1e-9 * np.abs(H_exact).max())
    for lin in out["lins"][1:]:
        jf = assemble_jacobian(fast, lin.jacobians)
        np.testing.assert_allclose(jf.T @ jf, H_irls, rtol=0, atol=1e-9 * np.abs(H_irls).max())
    with pytest.raises(TypeError, match=r"Factor\(corrector\)"):
        _se2_graph(Huber(1.0), corrector="triggs")
    with pytest.raises(TypeError, match=r"Factor\(kernel\)"):
        _se2_graph("huber")
    problem = pgo.pose_graph_problem(read_g2o(data_file("pose2example.txt")))
    with pytest.raises(TypeError, match=r"solve\(strategy\)"):
        graph_solve(problem, strategy="dogleg")
    with pytest.raises(TypeError, match=r"solve\(stopping\)"):
        graph_solve(problem, stopping={"max_steps": 3})
    with pytest.raises(ValueError, match=r"LambdaFactor\(factor\)"):
        LambdaFactor(1e-3, factor=1.0)
    with pytest.raises(ValueError, match=r"PCG\(rtol='exact'\)"):
        graph_solve(problem, linear_solver="pcg", cg=PCG(rtol="exact"))


def _random_elements(rng: np.random.Generator, name: str, n: int) -> np.ndarray:
    """Storage of n random elements of SE3, SE2, Sim3 or (from those) SO3, SO2, RxSO3."""
    if name in ("SE3", "SE2", "Sim3"):
        return random_poses(rng, name, n)
    if name == "SO3":
        return random_poses(rng, "SE3", n)[:, 3:]
    if name == "SO2":
        return random_poses(rng, "SE2", n)[:, 2:]
    return random_poses(rng, "Sim3", n)[:, 3:]  # RxSO3: [q, s]


def test_between_factor_takes_the_analytic_jacobian_unless_given_one():
    e = np.array([0, 1])
    z = SE3(jnp.asarray(random_poses(np.random.default_rng(0), "SE3", 2)))
    assert Factor(between_residual, [("p", e), ("p", e)], data=z).jacobian is between_jacobian

    def own(xi, xj, zz):
        return between_jacobian(xi, xj, zz)

    assert Factor(between_residual, [("p", e), ("p", e)], data=z, jacobian=own).jacobian is own
    # any other residual (even one that calls between_residual) is differentiated by autodiff
    wrapped = Factor(lambda a, b, c: between_residual(a, b, c), [("p", e), ("p", e)], data=z)
    assert wrapped.jacobian is None


@pytest.mark.parametrize("names", [("SE3", "SE2"), pytest.param(("Sim3", "SO3", "SO2", "RxSO3"),
                                                                marks=pytest.mark.slow)])
def test_between_jacobians_match_autodiff(names):
    rng = np.random.default_rng(4)
    groups = {"SE3": SE3, "SE2": SE2, "Sim3": Sim3, "SO3": SO3, "SO2": SO2, "RxSO3": RxSO3}
    data = {k: [groups[k](jnp.asarray(_random_elements(rng, k, 20))) for _ in range(3)]
            for k in names}

    @jax.jit(compiler_options=FAST_COMPILE)
    def run(data):
        out = {}
        for name, (xi, xj, z) in data.items():
            zero = jnp.zeros((xi.tangent_dim,))
            ji = jax.vmap(lambda a, b, c: jax.jacfwd(
                lambda d: between_residual(a.retract(d), b, c))(zero))(xi, xj, z)
            jj = jax.vmap(lambda a, b, c: jax.jacfwd(
                lambda d: between_residual(a, b.retract(d), c))(zero))(xi, xj, z)
            out[name] = (jax.vmap(between_jacobian)(xi, xj, z), ji, jj,
                         jax.vmap(between_residual)(xi, xj, z))
        return out

    for name, ((r, ji, jj), ri, rj, r_ref) in run(data).items():
        np.testing.assert_allclose(r, r_ref, rtol=0, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(ji, ri, rtol=0, atol=1e-9 * np.abs(ri).max(), err_msg=name)
        np.testing.assert_allclose(jj, rj, rtol=0, atol=1e-9 * np.abs(rj).max(), err_msg=name)
