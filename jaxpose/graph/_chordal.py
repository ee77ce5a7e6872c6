"""The chordal relaxation of :mod:`jaxpose.graph._init` in JAX: jit and vmap.

The same relaxation with the same weights (see :mod:`jaxpose.graph._init`: rotations by
linear least squares over the entries of the rotation matrices, projected to SO(3)/SO(2),
then the translations by one linear least-squares solve), written over a pose-graph
:class:`~jaxpose.graph.FactorGraph` (one SE3 or SE2 variable type, between factors, as
:func:`~jaxpose.graph.pose_graph_problem` builds it) with **dense** normal equations. So it
runs inside ``jax.jit`` and ``jax.vmap``: a batch of small pose graphs initialised and
solved in one program, and :func:`~jaxpose.graph.optimize_pose_graph` on graphs solved
densely with no host round trip. The normal matrices are (n·d)² (d = 3 in SE3, 2 in SE2),
so it takes graphs of at most 600 (:data:`DENSE_MAX`) tangent dimensions; larger graphs use the
host version (sparse, CHOLMOD), :func:`~jaxpose.graph.chordal_initialization`.

Differences of form, not of result (tests/graph/test_chordal_jax.py: 1e-9 of the host's
poses): the normal equations come from one product with the dense incidence matrix; the
weights enter as ``BᵀQB`` with Q = M (rotations) and Ω_tt (translations), no square roots,
and the translation target needs no pseudo-inverse (Ω_tt·Ω_tt⁺·Ω_tR = Ω_tR for a positive
semi-definite Ω); the rotations are projected by
:func:`~jaxpose.geometry.optimal_rotation` (det +1, its own derivative rule).

Anchors are the graph's held poses (``fixed``); every connected piece needs one (as
``pose_graph_problem(fix="first")`` arranges). Where the weights leave a pose's rotation
or translation free the normal matrix is singular: the solve is then retried with a
ridge of 1e-12 (float64; 10·eps in float32) of its largest diagonal entry, as on the
host. Information matrices are ``SᵀS`` of the factors' whitening ``S``; robust kernels
play no part. Differentiable by autodiff; a solve started from it does not depend on it
(:func:`~jaxpose.graph.solve`'s derivative with respect to the start is zero).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .._precision import FULL
from ..geometry._registration import _det3, optimal_rotation
from ..lie import SE2, SE3, series
from ..lie import _quaternion as quat
from ..lie._base import small_matmul
from ._factor import between_residual
from ._init import INIT_METHODS
from ._problem import FactorGraph, Variables, factor_residuals
from ._solve import GraphLinearSolver

Array = jax.Array

__all__ = ["chordal_poses", "initial_variables"]

DENSE_MAX = GraphLinearSolver().dense_max
"""Largest tangent dimension (6 per SE3 pose, 3 per SE2 pose) :func:`chordal_poses` takes:
the dense solver's default limit (``GraphLinearSolver().dense_max``, 600), so the graphs it
takes are those :func:`~jaxpose.graph.solve` solves densely by default."""


_mm = small_matmul


def _pose_graph(graph: Any, where: str) -> tuple[str, type, Array, Array, Array, Array, Array]:
    """(name, group, i, j, measurements (m, storage), information (m, r, r), held (n,))
    of a pose-graph FactorGraph; a clear error for anything else."""
    if not isinstance(graph, FactorGraph):
        raise TypeError(f"{where}(graph): expected a FactorGraph, got {type(graph).__name__}")
    names = graph.structure.names
    if len(graph.factors) != 1 or graph.factors[0].residual is not between_residual \
            or len(names) != 1:
        raise ValueError(f"{where}(graph): expected a pose graph (one SE3 or SE2 variable "
                         "type and one group of between factors, as pose_graph_problem "
                         "builds it)")
    name = names[0]
    x = graph.variables[name]
    group = type(x)
    if group not in (SE3, SE2):
        raise ValueError(f"{where}(graph): expected SE3 or SE2 poses, got {group.__name__}")
    if graph.size > DENSE_MAX:
        raise ValueError(f"{where}(graph): {graph.size} tangent dimensions; the dense "
                         f"relaxation takes at most DENSE_MAX = {DENSE_MAX} (use "
                         "chordal_initialization, the host version, for larger graphs)")
    f = graph.factors[0]
    m, r = f.count, group.tangent_dim
    s = jnp.eye(r, dtype=x.data.dtype) if f.sqrt_info is None else f.sqrt_info
    s = jnp.broadcast_to(s.astype(x.data.dtype), (m, r, r))
    held = graph.structure.free[0] == 0
    return name, group, f.indices[0], f.indices[1], f.data.data, _mm(s.mT, s), held


def _psd_clipped(m: Array) -> Array:
    """Each symmetric (m, 3, 3) M with its negative eigenvalues set to zero; the
    eigendecomposition runs only where some M has a negative principal minor, and only
    those M go through it (a repeated eigenvalue, as of an isotropic M, has no derivative
    there)."""
    c = jax.lax.stop_gradient(m)  # the test picks a branch; both are differentiable
    a, b, d = c[:, 0, 0], c[:, 1, 1], c[:, 2, 2]
    ab, ad, bd = c[:, 0, 1], c[:, 0, 2], c[:, 1, 2]
    psd = jnp.all(jnp.stack([a, b, d, a * b - ab * ab, a * d - ad * ad, b * d - bd * bd,
                             _det3(c)]) >= 0, axis=0)

    def clip() -> Array:
        safe = jnp.where(psd[:, None, None], jnp.diag(jnp.arange(1.0, 4.0, dtype=m.dtype)), m)
        w, v = jnp.linalg.eigh(safe)
        return jnp.where(psd[:, None, None], m,
                         _mm(v * jnp.clip(w, 0.0, None)[:, None, :], v.mT))

    return jax.lax.cond(jnp.all(psd), lambda: m, clip)


def _spd_solve(a: Array, b: Array, free: Array) -> Array:
    """X of A X = B by Cholesky; where A is not positive definite, retried with a ridge of
    1e-12 (float64; 10·eps in float32) of the largest diagonal entry of the ``free`` rows,
    as on the host."""
    def factor(ridge: Array) -> Array:
        return jnp.linalg.cholesky(a + jnp.diag(ridge * free))

    top = jnp.max(jnp.where(free, jnp.diagonal(a), 0.0))
    ridge = max(1e-12, 10 * float(jnp.finfo(a.dtype).eps)) * jnp.where(top > 0, top, 1.0)
    # the test factorises A once more, without derivatives (≤ DENSE_MAX rows: milliseconds):
    # a failed factor on the differentiated path, even discarded, sends 0·NaN back into A
    ok = jnp.all(jnp.isfinite(jnp.linalg.cholesky(jax.lax.stop_gradient(a))))
    low = jax.lax.cond(ok, lambda: factor(jnp.zeros((), a.dtype)), lambda: factor(ridge))
    return jax.scipy.linalg.cho_solve((low, True), b)


def _block_lstsq(i: Array, j: Array, bi: Array, bj: Array, q: Array, qc: Array,
                 held: Array, x_held: Array) -> Array:
    """X minimising Σ_e ``eᵀ·Q_e·e`` with ``e = Bi_e·X_i + Bj_e·X_j − C_e``, the vertices
    where ``held`` kept at ``x_held``. bi, bj: (m, k, d); q: (m, k, k) positive
    semi-definite; qc = Q·C: (m, k, p); x_held: (n, d, p). Returns X (n, d, p).

    The normal equations AᵀQA·X = AᵀQC come from the dense (m·k, n·d) A in one product:
    a handful of fused operations, where a scatter per block type made ~70 (a tiny graph's
    initialisation cost more than its LM iterations)."""
    n, d, p = x_held.shape
    m, k, _ = bi.shape
    x_fix = jnp.where(held[:, None, None], x_held, 0.0)
    # the held unknowns move to the right-hand side; their own rows become X = x_held
    qc = qc - _mm(q, _mm(bi, x_fix[i]) + _mm(bj, x_fix[j]))
    v = jnp.arange(n)
    at = lambda e: ((v == e[:, None]) & ~held)[:, None, :, None]  # noqa: E731
    a = (jnp.where(at(i), bi[:, :, None, :], 0.0)
         + jnp.where(at(j), bj[:, :, None, :], 0.0)).reshape(m, k, n * d)
    qa = jnp.concatenate([_mm(q, a), qc], -1).reshape(m * k, n * d + p)
    normal = jnp.matmul(a.reshape(m * k, n * d).T, qa, precision=FULL)
    held_rows = jnp.repeat(held, d)
    lhs = normal[:, :n * d] + jnp.diag(held_rows.astype(qc.dtype))
    rhs = jnp.where(held_rows[:, None], x_held.reshape(n * d, p), normal[:, n * d:])
    return _spd_solve(lhs, rhs, ~held_rows).reshape(n, d, p)


def _translations(i: Array, j: Array, rot: Array, zr: Array, zt: Array, info: Array,
                  phi: Array, vinv: Array, held: Array, t_held: Array) -> Array:
    """Translations minimising ½Σ rᵀΩr with the rotations (and so φ) fixed: the
    translation residual ``u = V⁻¹·Z_Rᵀ·(R_iᵀ(t_j − t_i) − t_z)`` weighted by Ω_tt, its
    target ``−Ω_tt⁺·Ω_tR·φ``; as Ω is positive semi-definite, Ω_tt·Ω_tt⁺·Ω_tR = Ω_tR,
    so Q·C = Ω_tt·V⁻¹·Z_Rᵀ·t_z − Ω_tR·φ needs no pseudo-inverse."""
    dt = zt.shape[-1]
    o_tt, o_tr = info[:, :dt, :dt], info[:, :dt, dt:]
    a = _mm(vinv, zr.mT)  # V⁻¹·Z_Rᵀ
    b = _mm(a, rot[i].mT)
    qc = _mm(o_tt, _mm(a, zt[..., None])) - _mm(o_tr, phi[..., None])
    return _block_lstsq(i, j, -b, b, o_tt, qc, held, t_held[..., None])[..., 0]


def _chordal_se3(x: Array, z: Array, info: Array, i: Array, j: Array, held: Array) -> Array:
    zr = quat.to_matrix(z[:, 3:])
    o_rr = info[:, 3:, 3:]
    mm = 0.5 * jnp.trace(o_rr, axis1=1, axis2=2)[:, None, None] * jnp.eye(3, dtype=x.dtype) - o_rr
    # unknowns X_v = R_vᵀ: (R_jᵀ − Z_ijᵀ·R_iᵀ) weighted by M = ½tr(Ω_R)·I − Ω_R
    eye = jnp.broadcast_to(jnp.eye(3, dtype=x.dtype), zr.shape)
    r_held = quat.to_matrix(x[:, 3:])
    xr = _block_lstsq(i, j, -zr.mT, eye, _psd_clipped(mm), jnp.zeros_like(zr), held,
                      r_held.mT)
    rot = jnp.where(held[:, None, None], r_held, optimal_rotation(xr.mT))
    q = quat.from_matrix(rot)
    phi = quat.log(quat.multiply(quat.conjugate(z[:, 3:]),
                                 quat.multiply(quat.conjugate(q[i]), q[j])))
    t = _translations(i, j, rot, zr, z[:, :3], info, phi, quat.jl_inv(phi, principal=True),
                      held, x[:, :3])
    return jnp.where(held[:, None], x, jnp.concatenate([t, q], -1))


def _chordal_se2(x: Array, z: Array, info: Array, i: Array, j: Array, held: Array) -> Array:
    cs_z = z[:, 2:4] / jnp.linalg.norm(z[:, 2:4], axis=-1, keepdims=True)
    cz, sz = cs_z[:, 0], cs_z[:, 1]
    # unknowns (c, s) per pose: (c_j + i s_j) − (c_i + i s_i)(c_z + i s_z), weight Ω_θθ
    rz = jnp.stack([cz, -sz, sz, cz], -1).reshape(-1, 2, 2)
    eye = jnp.broadcast_to(jnp.eye(2, dtype=x.dtype), rz.shape)
    w = jnp.clip(info[:, 2, 2], 0.0, None)[:, None, None] * eye
    cs_held = x[:, 2:4] / jnp.linalg.norm(x[:, 2:4], axis=-1, keepdims=True)
    cs = _block_lstsq(i, j, -rz, eye, w, jnp.zeros((len(rz), 2, 1), x.dtype), held,
                      cs_held[..., None])[..., 0]
    norm = jnp.linalg.norm(cs, axis=-1, keepdims=True)
    cs = jnp.where(norm > 0, cs / jnp.where(norm > 0, norm, 1.0), jnp.array([1.0, 0.0], x.dtype))
    cs = jnp.where(held[:, None], cs_held, cs)
    rot = jnp.stack([cs[:, 0], -cs[:, 1], cs[:, 1], cs[:, 0]], -1).reshape(-1, 2, 2)
    th = jnp.arctan2(cs[:, 1], cs[:, 0])
    dth = th[j] - th[i] - jnp.arctan2(sz, cz)
    phi = jnp.arctan2(jnp.sin(dth), jnp.cos(dth))  # θ of Z⁻¹·R_iᵀ·R_j
    h = series.half_cot_half_principal(phi * phi)  # V(θ)⁻¹ = [[h, θ/2], [−θ/2, h]]
    vinv = jnp.stack([h, 0.5 * phi, -0.5 * phi, h], -1).reshape(-1, 2, 2)
    t = _translations(i, j, rot, rz, z[:, :2], info, phi[:, None], vinv, held, x[:, :2])
    return jnp.where(held[:, None], x, jnp.concatenate([t, cs], -1))


def chordal_poses(graph: FactorGraph) -> Variables:
    """Chordal-relaxation starting poses of a pose-graph ``graph``, inside jit and vmap.

    Args:
        graph: a :class:`FactorGraph` of one SE3 or SE2 variable type and one group of
            between factors (:func:`~jaxpose.graph.pose_graph_problem`), of at most
            600 (:data:`DENSE_MAX`) tangent dimensions, with at least one held pose in every
            connected piece (``fix="first"`` or ``"file"``).

    Returns:
        ``{name: SE3 | SE2 (n,)}`` variables for :func:`~jaxpose.graph.solve`; the held
        poses unchanged. Matches the host :func:`~jaxpose.graph.chordal_initialization`
        (module docstring)."""
    name, group, i, j, z, info, held = _pose_graph(graph, "chordal_poses")
    x = eqx.error_if(graph.variables[name].data, ~jnp.any(held),
                     "chordal_poses(graph): no pose is held; the relaxation needs an anchor "
                     "in every connected piece (pose_graph_problem(fix='first' or 'file'))")
    relax = _chordal_se3 if group is SE3 else _chordal_se2
    return {name: group(relax(x, z, info, i, j, held))}


def _plain_costs(graph: FactorGraph, a: Variables, b: Variables) -> Array:
    """0.5·Σ rᵀΩr, kernels aside (the host ``pose_graph_cost``), at ``a`` and at ``b``
    (2,): one residual evaluation over the two pose sets (half the program of two)."""
    both = jax.tree.map(lambda u, v: jnp.stack([u, v]), a, b)
    r = jax.vmap(lambda x: factor_residuals(graph.factors[0], x))(both)
    return 0.5 * jnp.sum(r * r, axis=(1, 2))


def initial_variables(graph: FactorGraph, init: str = "auto") -> tuple[Variables, Array]:
    """Starting variables of a pose-graph ``graph`` and whether they are the chordal ones
    (a bool array), inside jit and vmap: :func:`~jaxpose.graph.initial_poses`' rule.

    ``init``: ``"odometry"`` keeps ``graph.variables``; ``"chordal"`` uses
    :func:`chordal_poses`; ``"auto"`` the chordal poses unless ``graph.variables`` have a
    lower cost ``0.5·Σ rᵀΩr`` (kernels aside) or the chordal cost is not finite."""
    if init not in INIT_METHODS:
        raise ValueError(f"initial_variables(init={init!r}): expected one of {INIT_METHODS}")
    if init == "odometry":
        _pose_graph(graph, "initial_variables")
        return graph.variables, jnp.asarray(False)
    chordal = chordal_poses(graph)
    if init == "chordal":
        return chordal, jnp.asarray(True)
    # the costs only choose (a boolean): no derivative through them
    fixed = jax.lax.stop_gradient(graph)
    c_file, c_chordal = _plain_costs(fixed, fixed.variables, jax.lax.stop_gradient(chordal))
    use = jnp.isfinite(c_chordal) & ~(c_file < c_chordal)
    return jax.tree.map(lambda a, b: jnp.where(use, a, b), chordal, graph.variables), use
