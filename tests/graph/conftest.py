"""Shared set-up and independent references for the factor-graph tests.

* float64 is enabled for the session; float32 cases pass float32 variables explicitly.
* ``data_file(name)``: a file of ``../shared/data/g2o`` (skips with a reason when absent).
* ``mixed_problem(...)``: a small random graph with every kind of variable the sparse
  path handles (SE3, SE2, Sim3, plain arrays) and factors that mix them, plus the
  information matrices it was built from (for references that do not use the code under
  test).
* References: ``dense_residual_fn`` (whitened residuals of the whole graph as a function
  of the full tangent vector, laid out as documented in ``jaxpose.graph._problem``: types
  in sorted-name order, each variable a contiguous slice) and ``assemble_jacobian``
  (Jacobian blocks of a ``GraphLinearization`` scattered into one dense matrix).
* ``jit_solve(**options)``: one jitted ``solve`` per option set, shared by the whole
  worker. XLA compilation of the LM loop dominates this suite's time (20–40 s per
  configuration on a loaded 2-core machine), so tests reuse compiled solvers: graphs of
  equal structure (same variable counts, factor types, kernel) reuse one executable, and
  values such as measurements, initial poses or the fixed-variable mask are leaves.
  These solvers are compiled at XLA backend optimisation level 0 (half the compile time;
  the numbers agree with the default level to rounding).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from jaxpose.graph import (  # noqa: E402
    Factor,
    FactorGraph,
    between_residual,
    prior_residual,
    vector_prior_residual,  # noqa: E402
)
from jaxpose.graph import solve as graph_solve  # noqa: E402
from jaxpose.lie import SE2, SE3, LieGroup, Sim3  # noqa: E402

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
G2O = DATA / "g2o"

# GTSAM 4.3 LevenbergMarquardtOptimizer, first pose fixed, cost 0.5·Σ rᵀΩr
# (../shared/data/README.md; the two small examples computed with gtsam.readG2o and the
# settings of bench/pgo.py).
GTSAM_COST = {
    "tinyGrid3D.g2o": 9.313909,
    "smallGrid3D.g2o": 5.179253e2,
    "parking-garage.g2o": 6.341924e-1,
    "sphere2500.g2o": 6.757010e2,
    "intel.g2o": 2.250212e1,
    "pose3example.txt": 18853.0207328572,
    "pose2example.txt": 0.5494864474988475,
}

FAST_COMPILE = {"xla_backend_optimization_level": 0}


def data_file(name: str) -> Path:
    path = G2O / name
    if not path.is_file():
        pytest.skip(f"reference data {path} not present (../shared/data is not checked out)")
    return path


_SOLVERS: dict[Any, Any] = {}


def jit_solve(**options: Any):
    """A jitted ``graph -> solve(graph, **options)``, one per option set per worker."""
    key = tuple(sorted(options.items()))
    if key not in _SOLVERS:
        _SOLVERS[key] = jax.jit(
            lambda graph: graph_solve(graph, **options), compiler_options=FAST_COMPILE
        )
    return _SOLVERS[key]


# ------------------------------------------------------------------------------------
# A small mixed graph
# ------------------------------------------------------------------------------------
def landmark_residual(x: SE3, p: jax.Array, z: jax.Array) -> jax.Array:
    """A point p seen from pose x: ``x⁻¹·p − z`` (mixes a group and an array variable)."""
    return x.inv().act(p) - z


def random_spd(rng: np.random.Generator, m: int, r: int) -> np.ndarray:
    a = rng.normal(size=(m, r, r))
    return a @ np.swapaxes(a, 1, 2) + r * np.eye(r)


def random_poses(rng: np.random.Generator, kind: str, n: int, sigma: float = 0.8) -> np.ndarray:
    """Storage of n random elements (numpy only: eager JAX ops would each compile)."""
    if kind == "SE2":
        th = rng.normal(size=n) * sigma
        return np.stack([*(rng.normal(size=(2, n)) * sigma), np.cos(th), np.sin(th)], 1)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    t = rng.normal(size=(n, 3)) * sigma
    if kind == "SE3":
        return np.concatenate([t, q], 1)
    assert kind == "Sim3"
    return np.concatenate([t, q, np.exp(0.3 * rng.normal(size=(n, 1)))], 1)


def relative_se2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE2 storage of a⁻¹·b."""
    m = np.linalg.inv(_pose_matrix("SE2", a)) @ _pose_matrix("SE2", b)
    return np.array([m[0, 2], m[1, 2], m[0, 0], m[1, 0]])


def mixed_problem(
    seed: int = 0, dtype: Any = jnp.float64, se2_kernel: Any = None, fixed: Any = None
) -> tuple[FactorGraph, list[np.ndarray | None]]:
    """(graph, information per factor group) over SE3, SE2, Sim3 and 3-vector variables.

    The SE2 between measurements agree with the poses up to 0.01 noise except the last
    one (an outlier), so a robust ``se2_kernel`` sees inliers and one outlier."""
    rng = np.random.default_rng(seed)
    group = {"SE3": SE3, "SE2": SE2, "Sim3": Sim3}
    rand = lambda kind, n: group[kind](jnp.asarray(random_poses(rng, kind, n), dtype))
    pose2 = random_poses(rng, "SE2", 4)
    variables = {
        "pose3": rand("SE3", 5),
        "pose2": SE2(jnp.asarray(pose2, dtype)),
        "sim3": rand("Sim3", 3),
        "point": jnp.asarray(rng.normal(size=(4, 3)), dtype),
    }
    e3 = np.array([[0, 1], [1, 2], [2, 3], [3, 4], [0, 3], [4, 1]])
    e2 = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
    z2 = np.stack([relative_se2(pose2[i], pose2[j] + 0.01 * np.r_[rng.normal(size=2), 0, 0])
                   for i, j in e2[:-1]] + [random_poses(rng, "SE2", 1)[0]])
    es = np.array([[0, 1], [1, 2], [2, 0]])
    obs = np.array([[0, 0], [1, 1], [2, 1], [3, 2], [4, 3], [0, 3]])  # (pose, point)
    info = [
        random_spd(rng, len(e3), 6),
        random_spd(rng, 1, 3)[0],
        None,
        random_spd(rng, len(obs), 3),
        random_spd(rng, 1, 6)[0],
        np.eye(3) * 4.0,
    ]
    factors = [
        Factor(between_residual, [("pose3", e3[:, 0]), ("pose3", e3[:, 1])],
               data=rand("SE3", len(e3)), information=info[0], name="between_se3"),
        Factor(between_residual, [("pose2", e2[:, 0]), ("pose2", e2[:, 1])],
               data=SE2(jnp.asarray(z2, dtype)), information=info[1], kernel=se2_kernel,
               name="between_se2"),
        Factor(between_residual, [("sim3", es[:, 0]), ("sim3", es[:, 1])],
               data=rand("Sim3", len(es)), name="between_sim3"),
        Factor(landmark_residual, [("pose3", obs[:, 0]), ("point", obs[:, 1])],
               data=jnp.asarray(rng.normal(size=(len(obs), 3)), dtype),
               information=info[3], name="landmark"),
        Factor(prior_residual, [("pose3", np.array([2]))], data=rand("SE3", 1),
               information=info[4], name="prior_se3"),
        Factor(vector_prior_residual, [("point", np.array([0, 2]))],
               data=jnp.asarray(rng.normal(size=(2, 3)), dtype), information=info[5],
               name="prior_point"),
    ]
    return FactorGraph(factors, variables, fixed=fixed), info


# ------------------------------------------------------------------------------------
# Independent dense references
# ------------------------------------------------------------------------------------
def _gather(value: Any, idx: Any) -> Any:
    return type(value)(value.data[idx]) if isinstance(value, LieGroup) else value[idx]


def layout(variables: dict[str, Any]) -> dict[str, tuple[int, int, int]]:
    """name → (offset, count, tangent dim), types in sorted-name order (documented layout)."""
    out, off = {}, 0
    for name in sorted(variables):
        v = variables[name]
        d = v.tangent_dim if isinstance(v, LieGroup) else v.shape[-1]
        out[name] = (off, v.shape[0], d)
        off += v.shape[0] * d
    return out


def sqrt_information(info: np.ndarray | None, m: int, r: int) -> np.ndarray:
    """Upper S with Ω = SᵀS per factor (m, r, r)."""
    if info is None:
        return np.broadcast_to(np.eye(r), (m, r, r))
    om = np.broadcast_to(info, (m, r, r))
    return np.swapaxes(np.linalg.cholesky(om), 1, 2)


def dense_residual_fn(graph: FactorGraph, variables: dict[str, Any], info: list[Any]):
    """delta (N,) → whitened residuals of every factor, flattened (M,), without kernels."""
    lay = layout(variables)

    def fn(delta: jax.Array) -> jax.Array:
        moved = {}
        for name, (off, n, d) in lay.items():
            blk = delta[off : off + n * d].reshape(n, d)
            v = variables[name]
            moved[name] = v.retract(blk) if isinstance(v, LieGroup) else v + blk
        out = []
        for f, om in zip(graph.factors, info, strict=True):
            args = [_gather(moved[s], i) for s, i in zip(f.slots, f.indices, strict=True)]
            r = jax.vmap(lambda *a, f=f: f.residual(*a[:-1], a[-1]))(*args, f.data)
            s = jnp.asarray(sqrt_information(om, r.shape[0], r.shape[1]), r.dtype)
            out.append(jnp.einsum("mij,mj->mi", s, r).reshape(-1))
        return jnp.concatenate(out)

    return fn


def assemble_jacobian(graph: FactorGraph, jacobians: Any) -> np.ndarray:
    """Scatter per-factor Jacobian blocks (m, r, d) into a dense (M, N) matrix."""
    lay = layout(graph.variables)
    n_cols = sum(n * d for _, n, d in lay.values())
    blocks = []
    for f, jac in zip(graph.factors, jacobians, strict=True):
        m, r = f.count, jac[0].shape[1]
        dense = np.zeros((m * r, n_cols))
        for slot, idx, j in zip(f.slots, f.indices, jac, strict=True):
            off, _, d = lay[slot]
            for e, v in enumerate(np.asarray(idx)):
                dense[e * r : (e + 1) * r, off + v * d : off + (v + 1) * d] += np.asarray(j[e])
        blocks.append(dense)
    return np.concatenate(blocks)


def csr_to_dense(values: Any, indices: Any, indptr: Any, n: int) -> np.ndarray:
    values, indices, indptr = map(np.asarray, (values, indices, indptr))
    rows = np.repeat(np.arange(n), np.diff(indptr))
    assert len({(int(a), int(b)) for a, b in zip(rows, indices)}) == len(rows), "duplicate CSR"
    out = np.zeros((n, n))
    np.add.at(out, (rows, indices), values)
    return out


def with_values(graph: FactorGraph, *, poses: Any = None, measurements: Any = None) -> Any:
    """The graph (single factor group, variable "pose") with other pose/measurement data."""
    if poses is not None:
        graph = eqx.tree_at(lambda g: g.variables["pose"].data, graph, poses)
    if measurements is not None:
        graph = eqx.tree_at(lambda g: g.factors[0].data.data, graph, measurements)
    return graph


def _skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])


def _pose_matrix(kind: str, p: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    if kind == "SE2":
        c, s = np.array([p[2], p[3]]) / np.hypot(p[2], p[3])
        return np.array([[c, -s, p[0]], [s, c, p[1]], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(p[3:7]).as_matrix()
    m[:3, 3] = p[:3]
    return m


def _log_matrix(kind: str, m: np.ndarray) -> np.ndarray:
    """SE(2)/SE(3) logarithm [ρ, φ] (translation first) of a homogeneous matrix."""
    from scipy.spatial.transform import Rotation

    if kind == "SE2":
        th = np.arctan2(m[1, 0], m[0, 0])
        if abs(th) < 1e-9:
            return np.array([m[0, 2], m[1, 2], th])
        a, b = np.sin(th) / th, (1 - np.cos(th)) / th
        v = np.array([[a, -b], [b, a]])
        return np.array([*np.linalg.solve(v, m[:2, 2]), th])
    phi = Rotation.from_matrix(m[:3, :3]).as_rotvec()
    th = np.linalg.norm(phi)
    w = _skew(phi)
    if th < 1e-8:
        v_inv = np.eye(3) - 0.5 * w + w @ w / 12.0
    else:
        v_inv = (np.eye(3) - 0.5 * w
                 + (1 - th * np.sin(th) / (2 * (1 - np.cos(th)))) / th**2 * (w @ w))
    return np.array([*(v_inv @ m[:3, 3]), *phi])


def numpy_pose_graph_cost(graph: Any, poses: np.ndarray | None = None) -> float:
    """0.5·Σ rᵀΩr with r = Log(Z⁻¹·Xi⁻¹·Xj), in numpy/scipy (independent of jaxpose)."""
    poses = graph.poses if poses is None else np.asarray(poses)
    total = 0.0
    for (i, j), z, om in zip(graph.edges, graph.measurements, graph.information, strict=True):
        xi, xj, zm = (_pose_matrix(graph.kind, p) for p in (poses[i], poses[j], z))
        r = _log_matrix(graph.kind, np.linalg.inv(zm) @ np.linalg.inv(xi) @ xj)
        total += 0.5 * r @ om @ r
    return float(total)


def dense_covariance(graph: FactorGraph, info: list[Any]) -> np.ndarray:
    """(H_ff)⁻¹ scattered into the full layout (zero rows/columns for fixed variables)."""
    jac = np.asarray(jax.jit(jax.jacfwd(dense_residual_fn(graph, graph.variables, info)))(
        jnp.zeros(graph.size)))
    st = graph.structure
    free = np.concatenate([np.repeat(np.asarray(f), d) for f, d in zip(st.free, st.dims)]) > 0
    h = jac.T @ jac
    cov = np.zeros_like(h)
    cov[np.ix_(free, free)] = np.linalg.inv(h[np.ix_(free, free)])
    return cov
