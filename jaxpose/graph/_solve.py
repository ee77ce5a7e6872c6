"""Levenberg–Marquardt on factor graphs (sparse path), one ``lax.while_loop``.

The iteration is :mod:`jaxpose.optim`'s own (``jaxpose.optim._iterate.trial``, shared with
``least_squares``); this module supplies the graph's block-sparse linearisation, the
Gauss–Newton matrix as an operator and the sparse linear solves. The configuration is
objects only: a damping :class:`~jaxpose.optim.Strategy` (default
:class:`~jaxpose.optim.LambdaFactor`, GTSAM's rule; :class:`~jaxpose.optim.Nielsen`,
``Constant``, ``Adaptive``, ``TrustRegion`` and ``Dogleg`` work too), a
:class:`~jaxpose.optim.Stopping`, a :class:`GraphLinearSolver`, a :class:`Damping` and a
:class:`PCG`; robust kernels and correctors are per factor (:class:`~jaxpose.graph.Factor`),
statuses :class:`~jaxpose.Results` codes. Each trial solves ``(H + λ·diag(D)) δ = −g``
with H = J̃ᵀJ̃ block-sparse, D = 1 (``damping="identity"``, GTSAM's default) or
D = clamp(diag H, min, max) (``"diagonal"``, Marquardt, as Ceres and GTSAM's
``diagonalDamping``), then evaluates the cost at X ⊕ δ. One
iteration is one trial: a finite trial that lowers the cost is accepted (gain ratio
ρ = (F(x) − F(x ⊕ δ)) / (L(0) − L(δ)) > 0), otherwise only the damping changes. The loop
only ever moves to an accepted (lower-cost) point, so the returned estimate is the best
seen.

Stopping (:func:`jaxpose.optim._stopping.check`): an accepted step lowering the cost by at
most ``cost_atol + cost_rtol·cost``; ‖g‖∞ ≤ ``gtol``; ‖δ‖ ≤ ``xtol``; a rejected trial
whose predicted decrease is at the cost's floating-point resolution; ``max_steps`` trials;
a rejection that cannot change the damping (λ at its bound: ``Results.DIVERGED``,
"stalled", best estimate kept).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import count_field
from .._compile import loops_compile_whole
from .._precision import full_precision
from ..optim import _iterate
from ..optim._solver import LevenbergMarquardt
from ..optim._stopping import Stopping, check_tolerance
from ..optim._strategies import LambdaFactor, NormalEquations, Strategy
from ..results import Results
from . import _linear as linear
from ._implicit import solve_differentiable
from ._problem import (
    FactorGraph,
    Variables,
    block_diagonal,
    check_structure,
    check_variables,
    csr_values,
    factor_residuals,
    free_flat,
    gradient,
    hessian_diagonal,
    hessian_vector,
    jtj_blocks,
    linearize,
    normal_dtype,
    residual_cost,
    retract_all,
    split,
    with_checked_kernels,
    zero_linearization,
)
from ._schur import reduced_solver, schur_parts, schur_step

Array = jax.Array

LINEAR_SOLVERS = ("auto", "sparse", "pcg", "dense", "schur")


class GraphSolution(eqx.Module):
    """Result of :func:`solve`.

    ``status``: a :class:`jaxpose.Results` code: 0 converged, 1 max_steps,
    2 diverged (stalled: damping exhausted; the estimate is the best found),
    3 non_finite (a non-finite cost or step stopped the solve: ``max_rejects`` such
    trials, or the budget ran out while every trial since the last accepted one was
    non-finite, or the gradient at the start is not finite; best estimate kept).
    ``iterations``: linear solves (accepted and rejected trials).
    ``history``: cost after each iteration (NaN beyond ``iterations``).
    ``linear_iterations``: total CG iterations (``"pcg"``; 0 for direct solvers)."""

    variables: Variables
    cost: Array
    initial_cost: Array
    iterations: Array
    status: Array
    history: Array
    linear_iterations: Array

    @property
    def status_name(self) -> str:
        """``status`` as text: converged, max_steps, diverged or non_finite
        (:meth:`jaxpose.Results.name_of`; an array of names for a batched solution)."""
        return Results.name_of(self.status)


def default_rtol(dtype: Any) -> float:
    """1e-10 in float64; 1e-6 (about 8 eps) in float32."""
    return 1e-10 if jnp.finfo(dtype).bits >= 64 else 1e-6


class GraphLinearSolver(eqx.Module):
    """How :func:`solve` solves each damped system (``linear_solver=``; a string is
    shorthand for ``GraphLinearSolver(method)``).

    ``method``: ``"sparse"`` (sparse Cholesky, CHOLMOD on the host through a callback; its
    symbolic analysis is reused across iterations), ``"pcg"`` (block-Jacobi preconditioned
    CG, any backend, see :class:`PCG`), ``"dense"`` (Cholesky, small problems), ``"schur"``
    (eliminate the graph's ``eliminate`` variable type, then a sparse Cholesky of the
    reduced system; a dense one on accelerators up to ``dense_max`` dimensions) or
    ``"auto"`` (schur when the graph eliminates a type, else dense up to ``dense_max``
    tangent dimensions, else sparse)."""

    method: str = eqx.field(default="auto", static=True)
    dense_max: int = count_field("GraphLinearSolver(dense_max)", minimum=0, default=600)

    def __check_init__(self) -> None:
        if self.method not in LINEAR_SOLVERS:
            raise ValueError(
                f"solve(linear_solver={self.method!r}): expected one of {LINEAR_SOLVERS}"
            )

    def resolve(self, graph: FactorGraph) -> str:
        """The concrete method for ``graph`` (``"auto"`` decided by its size)."""
        st = graph.structure
        if self.method == "schur" and st.schur is None:
            raise ValueError(
                "solve(linear_solver='schur'): the graph eliminates no variable type; build "
                "it with FactorGraph(..., eliminate=TYPE_NAME)"
            )
        if self.method != "auto":
            return self.method
        return ("schur" if st.schur is not None
                else "dense" if graph.size <= self.dense_max else "sparse")


class Damping(eqx.Module):
    """The damping matrix D of ``(H + λ·D) δ = −g`` (``damping=``; a string is shorthand
    for ``Damping(kind)``): ``"identity"`` (D = I, GTSAM's default) or ``"diagonal"``
    (D = clamp(diag H, min, max), Marquardt, as Ceres and GTSAM's ``diagonalDamping``)."""

    kind: str = eqx.field(default="identity", static=True)
    min: float = eqx.field(default=1e-6, static=True)
    max: float = eqx.field(default=1e32, static=True)

    def __check_init__(self) -> None:
        if self.kind not in ("identity", "diagonal"):
            raise ValueError(f"solve(damping={self.kind!r}): expected 'identity' or 'diagonal'")
        if not 0 < self.min <= self.max:
            raise ValueError(f"Damping(min, max): need 0 < min <= max, got {self.min}, "
                             f"{self.max}")


class PCG(eqx.Module):
    """Inner tolerance and budget of ``linear_solver="pcg"`` (``cg=``): ``rtol`` a float,
    or ``"inexact"`` for the inexact-Newton forcing sequence η = min(0.1, √(‖g‖/‖g₀‖))
    (Eisenstat–Walker style); ``max_iters`` CG iterations per solve."""

    rtol: float | str = eqx.field(default=1e-8, static=True)
    max_iters: int = count_field("PCG(max_iters)", default=2000)

    def __check_init__(self) -> None:
        if isinstance(self.rtol, str) and self.rtol != "inexact":
            raise ValueError(f"PCG(rtol={self.rtol!r}): expected a float or 'inexact'")
        if not isinstance(self.rtol, str):
            check_tolerance(self.rtol, "PCG(rtol)", positive=True)


class _Hessian:
    """H = J̃ᵀJ̃ as an operator (``H @ v``) for the strategies' step rules."""

    def __init__(self, graph: FactorGraph, lin: Any):
        self.graph, self.lin = graph, lin

    def __matmul__(self, v: Array) -> Array:
        return hessian_vector(self.graph, self.lin, v)


def damped_block_jacobi(graph: FactorGraph, lin: Any, add: Array) -> Any:
    """Block-Jacobi preconditioner of ``H + diag(add)`` (``add``: (N,) flat), H's diagonal
    blocks from the linearisation ``lin`` (:func:`~jaxpose.graph._linear.block_jacobi`)."""
    blocks = block_diagonal(graph, lin)
    return linear.block_jacobi(tuple(b + jax.vmap(jnp.diag)(a) for b, a in
                                     zip(blocks, split(graph, add), strict=True)))


class _SparseLinear:
    """The ``solve(jac, res, hess, grad, diag_add)`` protocol of the optim linear solvers
    on the sparse path: solves ``(H + diag(diag_add)) δ = −grad`` with H from the
    linearisation (fixed variables get an identity row). Records CG iterations."""

    def __init__(self, path: _GraphPath, lin: Any, cg_rtol: Any):
        self.path, self.lin, self.cg_rtol = path, lin, cg_rtol
        self.iterations = jnp.asarray(0, jnp.int32)

    def solve(self, jac: Any, res: Any, hess: Any, grad: Array, diag_add: Array) -> Array:
        path, lin, graph = self.path, self.lin, self.path.graph
        add = diag_add + (1.0 - path.free)
        if path.method == "pcg":
            x, its = linear.solve_pcg(
                lambda v: hessian_vector(graph, lin, v) + add * v, -grad,
                damped_block_jacobi(graph, lin, add), rtol=self.cg_rtol,
                max_iters=path.cg.max_iters,
            )
            self.iterations = self.iterations + jnp.asarray(its, jnp.int32)
            return x
        # the factorised paths work in normal_dtype (float64 for float32 problems when
        # x64 is on: a float32 JᵀJ of a long chain is indefinite); the step is cast back
        dtype = normal_dtype(grad.dtype)
        return self._factorised(grad.astype(dtype), add.astype(dtype)).astype(grad.dtype)

    def _factorised(self, grad: Array, add: Array) -> Array:
        path, lin = self.path, self.lin
        graph, st = path.graph, path.graph.structure
        if path.method == "schur":
            return schur_step(graph, schur_parts(graph, jtj_blocks(lin, grad.dtype), grad.dtype),
                              grad, add, reduced_solver(graph, path.dense_max))
        data = csr_values(graph, lin).at[st.diag_pos].add(add)
        if path.method == "dense":
            cholesky = linear.cholesky_solve_loops if path.dense_loops else linear.cholesky_solve
            return cholesky(linear.densify(data, path.dense_index, st.size), -grad)
        return linear.solve_sparse_direct(data, st.csr_indices, st.csr_indptr, -grad)


class _GraphPath:
    """The factor-graph path of the shared iteration (:mod:`jaxpose.optim._iterate`): the
    carried linearisation is ``(GraphLinearization, g)``, H a block-sparse operator."""

    def __init__(self, graph: FactorGraph, method: str, dense_max: int, damping: Damping,
                 cg: PCG, free: Array, g0_norm: Array | None, verbose: bool = False):
        self.graph, self.method, self.dense_max, self.damping = graph, method, dense_max, damping
        self.cg, self.free, self.g0_norm = cg, free, g0_norm
        st = graph.structure
        # "dense": H gathered from its CSR values (positions computed here, once, outside
        # the loop); without LAPACK when the loop then compiles whole (small systems; not
        # with verbose's printing, a host callback that keeps the loop split)
        self.dense_index = (linear.dense_index(st.csr_indices, st.csr_indptr, st.size)
                            if method == "dense" else None)
        self.dense_loops = (method == "dense" and st.size <= linear.SMALL_DENSE
                            and not verbose and loops_compile_whole())

    def linearize(self, variables: Variables) -> tuple[Any, Array, Array]:
        lin = linearize(self.graph, variables)
        g = gradient(self.graph, lin)
        # finite: the cost and the gradient (a non-finite Jacobian makes g non-finite)
        return (lin, g), lin.cost, jnp.isfinite(lin.cost) & jnp.all(jnp.isfinite(g))

    def normal(self, system: Any) -> NormalEquations:
        lin, g = system
        if self.damping.kind == "identity":
            scale = jnp.ones_like(g)
        else:
            scale = jnp.clip(hessian_diagonal(self.graph, lin), self.damping.min,
                             self.damping.max)
        return NormalEquations(None, None, _Hessian(self.graph, lin), g, scale,
                               jnp.zeros_like(g))

    def propose(self, rule: Any, sstate: Any, system: Any,
                normal: NormalEquations) -> tuple[Array, Array]:
        lin, g = system
        if self.cg.rtol == "inexact":
            eta = jnp.minimum(0.1, jnp.sqrt(jnp.linalg.norm(g)
                                            / jnp.maximum(self.g0_norm, 1e-300)))
        else:
            eta = self.cg.rtol
        solver = _SparseLinear(self, lin, eta)
        step = rule._propose(sstate, normal, solver) * self.free
        return step, solver.iterations

    def retract(self, variables: Variables, delta: Array) -> Variables:
        return retract_all(self.graph, variables, delta)


def default_stopping(max_steps: int = 100, dtype: Any = None) -> Stopping:
    """:func:`solve`'s default :class:`~jaxpose.optim.Stopping` (GTSAM-like): ``max_steps``
    trials, relative decrease :func:`default_rtol` of ``dtype`` (None: JAX's default float),
    no gradient or step tolerance."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    return Stopping(max_steps=max_steps, cost_rtol=default_rtol(dtype), gtol=0.0, xtol=0.0)


def _option(value: Any, cls: type, name: str) -> Any:
    if isinstance(value, str):
        return cls(value)
    if not isinstance(value, cls):
        raise TypeError(f"solve({name}): expected a string or {cls.__name__}, got "
                        f"{type(value).__name__}")
    return value


@eqx.filter_jit
@full_precision
def solve(
    graph: FactorGraph,
    variables: Variables | None = None,
    *,
    strategy: Strategy | None = None,
    stopping: Stopping | None = None,
    linear_solver: str | GraphLinearSolver = "auto",
    damping: str | Damping = "identity",
    cg: PCG | None = None,
    verbose: bool = False,
) -> GraphSolution:
    """Minimise ``0.5·Σ ρ(rᵀΩr)`` over the graph's variables with Levenberg–Marquardt.

    Args:
        graph: the :class:`FactorGraph` (its ``variables`` are the default start).
        variables: optional starting values with the same structure.
        strategy: a :class:`jaxpose.optim.Strategy` (default
            :class:`~jaxpose.optim.LambdaFactor`: GTSAM's λ ×/÷ 10 from 1e-5;
            :class:`~jaxpose.optim.Nielsen` as Ceres, ``Constant``, ``Adaptive``,
            ``TrustRegion``, ``Dogleg``).
        stopping: a :class:`jaxpose.optim.Stopping` (default :func:`default_stopping`:
            100 trials, relative decrease :func:`default_rtol`, no ``gtol``/``xtol``).
        linear_solver: a :class:`GraphLinearSolver` or its method name (``"auto"``,
            ``"sparse"``, ``"pcg"``, ``"dense"``, ``"schur"``).
        damping: a :class:`Damping` or its kind (``"identity"``: λ·I; ``"diagonal"``:
            λ·diag(H), Marquardt).
        cg: :class:`PCG` options of ``"pcg"`` (default ``PCG()``).
        verbose: print one line per iteration from inside jit.

    Compiled with ``eqx.filter_jit``: the graph's arrays (variables, measurements,
    information, weights) are traced and its structure and the options are static, so a
    repeated call on a graph of the same structure with new values reuses the program.

    Differentiable, exactly and at every order (``grad``, ``jvp``, ``jacfwd``,
    ``hessian``), with respect to every floating-point array of the graph (measurements,
    information, factor data) by the implicit function theorem at the solution, solved
    with ``linear_solver``'s method (see :mod:`jaxpose.graph._implicit`). The derivative
    with respect to the starting values is zero.
    """
    linear_solver = _option(linear_solver, GraphLinearSolver, "linear_solver")
    damping = _option(damping, Damping, "damping")
    cg = PCG() if cg is None else cg
    if not isinstance(cg, PCG):
        raise TypeError(f"solve(cg): expected a PCG, got {type(cg).__name__}")
    strategy = LambdaFactor() if strategy is None else strategy
    if not isinstance(strategy, Strategy):
        raise TypeError(
            f"solve(strategy): expected a jaxpose.optim Strategy, got {type(strategy).__name__}"
        )
    if stopping is not None and not isinstance(stopping, Stopping):
        raise TypeError(
            f"solve(stopping): expected a jaxpose.optim Stopping, got {type(stopping).__name__}"
        )
    graph = check_structure(graph, "solve")
    x0 = graph.variables if variables is None else variables
    check_variables(graph, x0, "solve(variables)")
    graph = with_checked_kernels(graph)
    return solve_differentiable(
        _run, graph, x0, strategy=strategy, stopping=stopping, linear_solver=linear_solver,
        damping=damping, cg=cg, verbose=verbose,
    )


def _run(
    graph: FactorGraph,
    x0: Variables,
    *,
    strategy: Strategy,
    stopping: Stopping | None,
    linear_solver: GraphLinearSolver,
    damping: Damping,
    cg: PCG,
    verbose: bool,
) -> GraphSolution:
    """The Levenberg–Marquardt loop of :func:`solve` (options already checked)."""
    method = linear_solver.resolve(graph)
    # the residuals are evaluated in the loop only (its first trial linearises at x0): a
    # second copy of them before the loop made the compiled program ~15 % larger
    def residuals_and_cost(x: Variables) -> tuple[list[Array], Array]:
        res = [factor_residuals(f, x) for f in graph.factors]
        return res, residual_cost(graph, res)

    res0, cost0 = jax.eval_shape(residuals_and_cost, x0)
    dtype = cost0.dtype
    stopping = default_stopping(dtype=dtype) if stopping is None else stopping
    free = free_flat(graph, dtype)
    rule = LevenbergMarquardt(strategy=strategy)
    g0_norm = None
    if method == "pcg" and cg.rtol == "inexact":  # its forcing term: relative to ‖g(x0)‖
        g0_norm = jnp.linalg.norm(gradient(graph, linearize(graph, x0)))
    path = _GraphPath(graph, method, linear_solver.dense_max, damping, cg, free, g0_norm,
                      verbose)
    # the loop's first trial linearises at x0 (the Jacobians are traced once, in the
    # body; compilation time scales with the traced program); until then the carried
    # system is a zero placeholder of its layout
    system0 = (zero_linearization(graph, res0), jnp.zeros((graph.structure.size,), dtype))
    placeholder = jnp.asarray(jnp.nan, dtype)  # the first trial sets the initial cost
    state = _iterate.init(rule, x0, system0, placeholder, stopping, history=True)
    out = jax.lax.while_loop(
        lambda s: ~s.done,
        lambda s: _iterate.trial(rule, path, s, stopping, verbose=verbose, label="graph.solve"),
        state,
    )
    solution = GraphSolution(
        variables=out.params,
        cost=out.cost,
        initial_cost=out.initial_cost,
        iterations=out.num_steps,
        status=out.status,
        history=out.history[1:],
        linear_iterations=out.linear_iterations,
    )
    return _iterate.check_initial_cost(
        solution, out.initial_cost, "solve: the cost is not finite at the initial variables "
        "(check measurements, information matrices and initial values)")


def summary(sol: GraphSolution) -> dict[str, Any]:
    """Plain-Python summary of a solution."""
    return {
        "status": sol.status_name,
        "iterations": int(sol.iterations),
        "initial_cost": float(sol.initial_cost),
        "final_cost": float(sol.cost),
    }
