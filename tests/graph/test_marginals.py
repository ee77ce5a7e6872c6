"""Marginal covariances of factor graphs (``jaxpose.graph.marginals``).

References independent of the code under test: the inverse of the Gauss–Newton matrix
assembled densely in numpy from ``jax.jacfwd`` of the whole graph's whitened residual
(``conftest.dense_residual_fn``), and GTSAM's ``Marginals`` (``marginalCovariance``,
``jointMarginalCovariance``) on the g2o files, linearised at the same values. GTSAM needs a
prior for the gauge: the exact comparisons (1e-9 relative) give both libraries the same
prior factor on pose 0; a separate check compares jaxpose's fixed first pose with a tight
GTSAM prior. Charts: se3 ``[ρ, φ]`` vs GTSAM Pose3 ``[ω, v]`` (``se3_to_gtsam``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose import read_g2o
from jaxpose.datasets import synthetic_bal
from jaxpose.graph import (
    Factor,
    FactorGraph,
    Marginals,
    cost,
    default_stopping,
    marginals,
    prior_residual,
    se3_to_gtsam,
)
from jaxpose.graph import _ba as bal_graph
from jaxpose.graph import _pgo as pgo
from jaxpose.graph._selinv import inverse_entries, supernodal_available

from .conftest import (
    FAST_COMPILE,
    data_file,
    dense_covariance,
    jit_solve,
    mixed_problem,
)

PRIOR_SIGMA = 0.1




def _blocks(cov, graph, name):
    st = graph.structure
    k = st.names.index(name)
    o, n, d = st.offsets[k], st.counts[k], st.dims[k]
    return np.stack([cov[o + i * d : o + (i + 1) * d, o + i * d : o + (i + 1) * d]
                     for i in range(n)])


def _jit_marginals(**options):
    return jax.jit(lambda g, v: marginals(g, v, **options), compiler_options=FAST_COMPILE)


def test_mixed_graph_matches_dense_inverse():
    """Every variable type (SE3, SE2, Sim3, points), fixed variables, joint pairs; the
    dense, sparse (selected inversion) and PCG methods in one compiled program."""
    graph, info = mixed_problem(seed=3, fixed={"pose3": [0], "pose2": [1], "sim3": [0]})
    ref = dense_covariance(graph, info)
    pairs = [(("pose3", 1), ("point", 2)), (("pose2", 0), ("pose2", 3)),
             (("pose3", 0), ("pose3", 4))]
    methods = ("dense", "sparse", "pcg")
    results = jax.jit(
        lambda g: [marginals(g, None, pairs=pairs, method=m) for m in methods],
        compiler_options=FAST_COMPILE)(graph)
    st = graph.structure
    tol = dict(rtol=1e-9, atol=1e-12 * np.abs(ref).max())
    for m in results:
        assert isinstance(m, Marginals)
        for name in st.names:
            np.testing.assert_allclose(m.covariances[name], _blocks(ref, graph, name), **tol)
        for ((ta, ia), (tb, ib)), joint in zip(pairs, m.joint, strict=True):
            ka, kb = st.names.index(ta), st.names.index(tb)
            sl = np.r_[st.offsets[ka] + ia * st.dims[ka] + np.arange(st.dims[ka]),
                       st.offsets[kb] + ib * st.dims[kb] + np.arange(st.dims[kb])]
            np.testing.assert_allclose(joint, ref[np.ix_(sl, sl)], **tol)
        # fixed variables: zero blocks
        assert np.all(np.asarray(m.covariances["pose3"][0]) == 0)
        assert np.all(np.asarray(m.joint[2])[:6] == 0)



def test_pcg_that_does_not_converge_raises():
    """A CG budget too small for the requested accuracy raises (eagerly and under jit),
    never returns an inexact covariance; enough iterations give numpy's inverse."""
    from jaxpose import synthetic_pose_graph

    pg, _ = synthetic_pose_graph("SE2", n_poses=8, noise=(0.05, 0.05), seed=0)
    graph = pgo.pose_graph_problem(pg)
    with pytest.raises(Exception, match=r"did not reach cg_rtol=1e-12 within cg_max_iters=2"):
        jax.block_until_ready(marginals(graph, None, method="pcg", cg_max_iters=2).covariances)
    run = jax.jit(lambda g: marginals(g, None, method="pcg", cg_max_iters=2).covariances,
                  compiler_options=FAST_COMPILE)
    with pytest.raises(Exception, match="raise cg_max_iters, or use method='sparse'"):
        jax.block_until_ready(run(graph))
    ref = dense_covariance(graph, [np.asarray(pg.information)])
    got = marginals(graph, None, method="pcg", cg_max_iters=500).covariances["pose"]
    np.testing.assert_allclose(got, _blocks(ref, graph, "pose"), rtol=1e-8,
                               atol=1e-11 * np.abs(ref).max())
    # float32 with the default cg_rtol (1e-12, below its resolution): CG to 1e-5, no error
    g32, g64 = _small_se2(jnp.float32), _small_se2()
    c32 = marginals(g32, None, "pose", method="pcg").covariances["pose"]
    c64 = marginals(g64, None, "pose", method="dense").covariances["pose"]
    assert c32.dtype == jnp.float32
    np.testing.assert_allclose(c32, c64, rtol=2e-3, atol=2e-3 * np.abs(np.asarray(c64)).max())

def test_selected_inverse_all_entries():
    """Selected inversion (supernodal Takahashi) + off-pattern solves = numpy's inverse."""
    rng = np.random.default_rng(1)
    n = 200
    a = np.where(rng.random((n, n)) < 0.02, rng.normal(size=(n, n)), 0.0)
    a = a + a.T + np.diag(np.full(n, 10.0))
    rows, cols = np.nonzero(a)
    indptr = np.searchsorted(rows, np.arange(n + 1))
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    got = inverse_entries(a[rows, cols], cols, indptr, i, j)
    np.testing.assert_allclose(got, np.linalg.inv(a), rtol=1e-10, atol=1e-14)
    a[5, 5] = -50.0  # indefinite: NaN, never a wrong number
    assert np.all(np.isnan(inverse_entries(a[rows, cols], cols, indptr, i[:2], j[:2])))


def test_supernodal_factor_is_used():
    pytest.importorskip("cholespy")
    assert supernodal_available()


def test_schur_camera_marginals_match_full_system():
    """BA: camera marginals from the reduced matrix S equal those of the full H."""
    problem, _ = synthetic_bal(n_cameras=4, n_points=30, obs_per_point=3, seed=2)
    graph = bal_graph.bundle_adjustment_problem(problem, fixed_cameras=(0, 1))
    schur = _jit_marginals(method="schur", pairs=[(("pose", 2), ("intrinsics", 3))])(
        graph, graph.variables)
    full = _jit_marginals(variables=["intrinsics", "pose"], method="sparse",
                          pairs=[(("pose", 2), ("intrinsics", 3))])(graph, graph.variables)
    assert set(schur.covariances) == {"intrinsics", "pose"}
    for name in ("intrinsics", "pose"):
        np.testing.assert_allclose(schur.covariances[name], full.covariances[name],
                                   rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(schur.joint[0], full.joint[0], rtol=1e-8, atol=1e-14)
    with pytest.raises(ValueError, match="eliminated type"):
        marginals(graph, variables="point", method="schur")


def _small_se2(dtype=jnp.float64):
    from jaxpose import synthetic_pose_graph

    pg, _ = synthetic_pose_graph("SE2", n_poses=8, noise=(0.05, 0.05), seed=0)
    return pgo.pose_graph_problem(pg, dtype=dtype)


def test_jit_vmap_and_float32():
    graph = _small_se2()
    fn = jax.jit(lambda g, v: marginals(g, v, "pose", pairs=np.array([[1, 2], [0, 7]]),
                                        method="dense"), compiler_options=FAST_COMPILE)
    m = fn(graph, graph.variables)
    assert m.covariances["pose"].shape == (8, 3, 3) and m.joint.shape == (2, 6, 6)
    # vmap over two linearisation points = one at a time
    poses = graph.variables["pose"].data
    moved = poses.at[:, :2].multiply(1.1)
    both = {"pose": type(graph.variables["pose"])(jnp.stack([poses, moved]))}
    mv = jax.jit(jax.vmap(lambda v: marginals(graph, v, "pose", method="dense")),
                 compiler_options=FAST_COMPILE)(both)
    one = fn(graph, {"pose": type(graph.variables["pose"])(moved)})
    np.testing.assert_allclose(mv.covariances["pose"][1], one.covariances["pose"], rtol=1e-10)
    np.testing.assert_allclose(mv.covariances["pose"][0], m.covariances["pose"], rtol=1e-10)
    # float32: runs (dense and sparse), close to float64
    g32 = _small_se2(jnp.float32)
    c32 = jax.jit(lambda g: [marginals(g, None, "pose", method=k).covariances["pose"]
                             for k in ("dense", "sparse")], compiler_options=FAST_COMPILE)(g32)
    ref = np.asarray(m.covariances["pose"])
    for c in c32:
        assert c.dtype == jnp.float32
        np.testing.assert_allclose(c, ref, rtol=2e-3, atol=2e-3 * np.abs(ref).max())


def test_float32_marginals_of_a_stiff_graph_are_factorised_in_float64():
    """Every other edge 1e8 times stiffer: H's condition passes float32's 1e7, and a float32
    JᵀJ is indefinite, so the covariances were NaN, silently (dense and sparse). H is
    formed in float64 (x64 on), the covariances come back in float32."""
    import dataclasses

    from jaxpose import synthetic_pose_graph

    pg, _ = synthetic_pose_graph("SE2", n_poses=30, shape="circle", seed=1, noise=(0.05, 0.05))
    info = pg.information.copy()
    info[::2] *= 1e8
    pg = dataclasses.replace(pg, information=info)
    g64 = pgo.pose_graph_problem(pg)
    ref = np.asarray(marginals(g64, None, "pose", method="dense").covariances["pose"])
    g32 = pgo.pose_graph_problem(pg, dtype=jnp.float32)
    c32 = jax.jit(lambda g: [marginals(g, None, "pose", method=k).covariances["pose"]
                             for k in ("dense", "sparse")], compiler_options=FAST_COMPILE)(g32)
    for c in c32:
        assert c.dtype == jnp.float32
        np.testing.assert_allclose(c, ref, rtol=0, atol=1e-5 * np.abs(ref).max())


def test_gradient_through_dense_marginals():
    """d trace(Σ_5) / d(scale of the positions) vs central finite differences."""
    graph = _small_se2()
    poses = graph.variables["pose"].data
    group = type(graph.variables["pose"])

    @jax.jit
    def f(scale):
        v = {"pose": group(poses.at[:, :2].multiply(scale))}
        return jnp.trace(marginals(graph, v, "pose", method="dense").covariances["pose"][5])

    g = jax.jit(jax.grad(f))(1.0)
    h = 1e-5
    fd = (f(1.0 + h) - f(1.0 - h)) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-6)
    assert abs(float(g)) > 1e-8


def test_bad_input():
    graph, _ = mixed_problem(seed=0, fixed={"pose3": [0]})
    with pytest.raises(ValueError, match="method"):
        marginals(graph, method="qr")
    with pytest.raises(KeyError, match="unknown variable type"):
        marginals(graph, variables="cam")
    with pytest.raises(IndexError, match="out of range"):
        marginals(graph, variables={"pose3": [7]})
    with pytest.raises(ValueError, match="one variable type"):
        marginals(graph, variables=["pose3", "point"], pairs=[[0, 1]])
    with pytest.raises(ValueError, match="\\(P, 2\\)"):
        marginals(graph, variables="pose3", pairs=[(1, 2, 3)])
    with pytest.raises(ValueError, match="pairs\\[0\\]"):
        marginals(graph, pairs=[(("pose3", 1),)])
    with pytest.raises(TypeError, match="FactorGraph"):
        marginals("graph")
    with pytest.raises(ValueError, match="eliminates no variable type"):
        marginals(graph, method="schur")


# ------------------------------------------------------------------------------------
# GTSAM
# ------------------------------------------------------------------------------------
def _gtsam_values(gtsam, kind, poses):
    vals = gtsam.Values()
    for k, p in enumerate(np.asarray(poses)):
        if kind == "SE3":
            vals.insert(k, gtsam.Pose3(gtsam.Rot3.Quaternion(p[6], p[3], p[4], p[5]), p[:3]))
        else:
            vals.insert(k, gtsam.Pose2(p[0], p[1], np.arctan2(p[3], p[2])))
    return vals


def _gtsam_marginals(gtsam, path, kind, poses, sigma):
    graph, _ = gtsam.readG2o(str(path), kind == "SE3")
    vals = _gtsam_values(gtsam, kind, poses)
    full = gtsam.NonlinearFactorGraph(graph)
    d = 6 if kind == "SE3" else 3
    prior = gtsam.PriorFactorPose3 if kind == "SE3" else gtsam.PriorFactorPose2
    at = vals.atPose3(0) if kind == "SE3" else vals.atPose2(0)
    full.add(prior(0, at, gtsam.noiseModel.Isotropic.Sigma(d, sigma)))
    return gtsam.Marginals(full, vals), graph.error(vals)


def _with_prior(pg, poses, sigma):
    """jaxpose problem: the file's edges + the same isotropic prior on pose 0, no fixing."""
    base = pgo.pose_graph_problem(pg, fix="none")
    group = type(base.variables["pose"])
    values = {"pose": group(jnp.asarray(poses))}
    d = base.variables["pose"].tangent_dim
    prior = Factor(prior_residual, [("pose", np.array([0]))], data=group(jnp.asarray(poses)[:1]),
                   information=np.eye(d) / sigma**2, name="prior")
    return FactorGraph([base.factors[0], prior], values), values


def _to_gtsam_chart(cov, kind):
    if kind != "SE3":
        return np.asarray(cov)
    d = cov.shape[-1]
    p = np.concatenate([np.r_[k + 3 : k + 6, k : k + 3] for k in range(0, d, 6)])
    return np.asarray(cov)[..., p, :][..., :, p]


def _compare_with_gtsam(name, poses=None, method="auto", keys=None, rtol=1e-9):
    gtsam = pytest.importorskip("gtsam")
    path = data_file(name)
    pg = read_g2o(path)
    poses = np.asarray(pg.poses if poses is None else poses)
    n = poses.shape[0]
    graph, values = _with_prior(pg, poses, PRIOR_SIGMA)
    pairs = np.array([[0, n - 1], [1, 2], [n // 2, n // 3]])
    m = _jit_marginals(variables="pose", pairs=pairs, method=method)(graph, values)
    ref, err = _gtsam_marginals(gtsam, path, pg.kind, poses, PRIOR_SIGMA)
    # the same linearisation point and cost in both libraries
    np.testing.assert_allclose(float(cost(graph, values)), err, rtol=1e-9)
    cov = _to_gtsam_chart(m.covariances["pose"], pg.kind)
    keys = range(n) if keys is None else keys
    worst = 0.0
    for k in keys:
        g = ref.marginalCovariance(k)
        worst = max(worst, np.abs(cov[k] - g).max() / np.abs(g).max())
    assert worst <= rtol, worst
    joint = _to_gtsam_chart(m.joint, pg.kind)
    for (a, b), jm in zip(pairs, joint, strict=True):
        g = ref.jointMarginalCovariance(gtsam.KeyVector([int(a), int(b)])).fullMatrix()
        assert np.abs(jm - g).max() <= rtol * np.abs(g).max()
    return err


@pytest.mark.peer
@pytest.mark.parametrize("name", ["pose2example.txt", "tinyGrid3D.g2o",
                                  pytest.param("smallGrid3D.g2o", marks=pytest.mark.slow)])
def test_gtsam_marginals_small(name):
    """At the file's values (residuals far from zero, so Jacobians at non-zero residuals
    are exercised); dense for the small ones."""
    _compare_with_gtsam(name, method="auto")


@pytest.mark.peer
def test_fixed_gauge_vs_tight_gtsam_prior():
    """jaxpose holds pose 0 exactly; GTSAM with a σ = 1e-7 prior approaches it."""
    gtsam = pytest.importorskip("gtsam")
    path = data_file("tinyGrid3D.g2o")
    pg = read_g2o(path)
    problem = pgo.pose_graph_problem(pg)
    m = _jit_marginals(variables="pose", method="dense")(problem, problem.variables)
    ref, _ = _gtsam_marginals(gtsam, path, pg.kind, pg.poses, 1e-7)
    cov = se3_to_gtsam(m.covariances["pose"])
    assert np.all(cov[0] == 0) and np.abs(ref.marginalCovariance(0)).max() < 1e-12
    for k in range(1, pg.n_poses):
        g = ref.marginalCovariance(k)
        np.testing.assert_allclose(cov[k], g, rtol=0, atol=1e-8 * np.abs(g).max())


# intel (cond(H) ≈ 3.7e8 with the σ = 0.1 prior) and parking-garage are ill-conditioned:
# κ·eps ≈ 1e-7, so the two libraries differ at that level. Measured for intel: jaxpose's
# sparse result equals numpy's dense inverse of the same H to 3e-10, GTSAM's differs from it
# by 1.2e-7 — the 1e-9 bar holds where the conditioning allows (sphere2500, smallGrid3D).
GTSAM_RTOL = {"parking-garage.g2o": 1e-7, "sphere2500.g2o": 1e-9, "intel.g2o": 5e-7}


@pytest.mark.slow
@pytest.mark.peer
@pytest.mark.parametrize("name", ["parking-garage.g2o", "sphere2500.g2o", "intel.g2o"])
def test_gtsam_marginals_at_solution(name):
    """The issue's acceptance files, at jaxpose's solution, all pose marginals (sparse)."""
    pg = read_g2o(data_file(name))
    run = jit_solve(linear_solver="sparse", stopping=default_stopping(200))
    sol = run(pgo.pose_graph_problem(pg))
    assert sol.status_name == "converged"
    _compare_with_gtsam(name, poses=sol.variables["pose"].data, method="sparse",
                        rtol=GTSAM_RTOL[name])


def test_plot_pose_graphs_leaves_the_matplotlib_backend_alone(tmp_path):
    """The plot switched the process's backend to Agg (matplotlib.use), which stops a
    notebook's inline figures; it draws on a Figure of its own now."""
    matplotlib = pytest.importorskip("matplotlib")
    from jaxpose.plot import plot_pose_graphs

    before = matplotlib.get_backend()
    matplotlib.use("pdf")
    try:
        poses = np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 1.0, 0.0], [1.0, 1.0, 0.0, 1.0]])
        path = tmp_path / "graph.png"
        plot_pose_graphs(str(path), "SE2", poses, poses, np.array([[0, 1], [1, 2]]),
                         covariances=np.broadcast_to(np.eye(3) * 0.01, (3, 3, 3)))
        assert matplotlib.get_backend() == "pdf"
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    finally:
        matplotlib.use(before)


def test_position_ellipses_geometry():
    """World-frame position covariance R Σ_ρρ Rᵀ and the 2σ ellipse axes (closed forms)."""
    from jaxpose.plot import ellipse_axes, position_covariances

    poses = np.array([[1.0, 2.0, 0.0, 1.0]])  # SE2 rotated by 90°
    cov = np.diag([4.0, 1.0, 0.5])[None]
    world = position_covariances("SE2", poses, cov)
    np.testing.assert_allclose(world[0], np.diag([1.0, 4.0]), atol=1e-12)
    w, h, angle = ellipse_axes(world)
    np.testing.assert_allclose([w[0], h[0]], [8.0, 4.0])  # 2σ full axes: 2·2·√4, 2·2·√1
    assert abs(abs(angle[0]) - 90.0) < 1e-9
    # SE3: 90° about z, the same position block
    q = np.r_[0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)]
    cov3 = np.zeros((1, 6, 6))
    cov3[0, :3, :3] = np.diag([4.0, 1.0, 9.0])
    world3 = position_covariances("SE3", np.r_[0, 0, 0, q][None], cov3)
    np.testing.assert_allclose(world3[0], np.diag([1.0, 4.0, 9.0]), atol=1e-12)


def test_pcg_marginals_differentiate_like_dense():
    # CG inside custom_linear_solve: grad and jacfwd went through lineax's preconditioner
    # options and crashed ("Unexpected tangent")
    import equinox as eqx

    from jaxpose import synthetic_pose_graph
    from jaxpose.graph import _pgo as pgo
    from jaxpose.graph import marginals, solve

    base = pgo.pose_graph_problem(synthetic_pose_graph("SE2", n_poses=8, loop_closures=3,
                                                       seed=1)[0])
    sol = solve(base)

    def total(scale, method):
        f = eqx.tree_at(lambda f: f.sqrt_info, base.factors[0],
                        base.factors[0].sqrt_info * scale)
        graph = eqx.tree_at(lambda g: g.factors, base, (f,))
        cov = marginals(graph, sol, method=method, variables="pose").covariances["pose"]
        return jnp.sum(cov[3])

    # Σ ∝ 1/scale²: d/dscale Σ = −2 Σ at scale 1
    ref = -2.0 * float(total(1.0, "dense"))
    for how in (jax.grad, jax.jacfwd):
        np.testing.assert_allclose(float(how(total)(1.0, "pcg")), ref, rtol=1e-8)
