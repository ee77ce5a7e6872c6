"""Learning per-observation weights for bundle adjustment, through the BA solve.

The bundle-adjustment counterpart of :mod:`learned_weights` (pose graphs), at a smaller
size. A synthetic BAL problem (:func:`jaxpose.datasets.synthetic_bal`: cameras on a ring,
1-pixel noise) has a seeded fraction of its observations replaced by gross outliers (the
observed pixel moved by a uniform offset of up to ``OUTLIER_PX`` in each coordinate). It
is bundle-adjusted as :func:`jaxpose.graph.optimize_bal` does —
:func:`~jaxpose.graph.bundle_adjustment_problem`, then :func:`jaxpose.graph.solve` with
Schur elimination of the points, Marquardt damping and Nielsen's rule — with cameras 0 and
1 held at their true values (BA's gauge, so every solution shares one frame; held at
``synthetic_bal``'s perturbed starting values, two whole cameras would fix 12 degrees of
freedom against the gauge's 7 and contradict the data by several pixels, which makes their
true observations look like outliers: :func:`held_at_truth`).

Baseline: a fixed robust kernel (Huber, Cauchy, Geman–McClure) on every observation, its
scale tuned on the training draws over ``SCALES`` × √τ (τ: the χ² 0.99 quantile of a
2-dof pixel error at the noise level). Learned: from the best kernel's solution each
observation gets three features — ``log(1 + s/τ)`` and ``τ/(s + τ)`` of its squared
reprojection error s, and ``log(1 + s/(m + τ))`` with m the median of s over the other
observations of its point (an outlier stands out among its point's observations) — and the
:class:`learned_weights.WeightNet` corrects the kernel's IRLS weight ρ'(s) in log-odds.
The weighted problem (:func:`jaxpose.graph.weighted_graph`) is solved again from the
kernel's solution and the network trained by Adam on the mean squared error of its points
against each training draw's own oracle solution (the outliers at weight 0); the gradient
flows through the BA solve by implicit differentiation (one Schur-eliminated solve of the
exact Hessian per backward pass). Held-out draws are scored by the points' RMS error
against the uncorrupted problem's solution.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxpose.graph as jg
from jaxpose.datasets import synthetic_bal
from jaxpose.graph import chi2_quantile
from jaxpose.graph._problem import factor_residuals
from jaxpose.io import BALProblem
from jaxpose.optim import Nielsen

try:  # as a package module (tests, bench) or next to the notebook
    from . import learned_weights as lw
except ImportError:  # pragma: no cover - run from notebooks/_examples
    import learned_weights as lw

KERNELS = lw.KERNELS
SCALES = lw.SCALES
OUTLIER_PX = 40.0  # largest offset of an outlier, pixels per coordinate
PIXEL_NOISE = 1.0
N_FEATURES = 3
FIXED = (0, 1)  # cameras held: BA's gauge


def threshold() -> float:
    """τ: the χ² 0.99 quantile of a 2-dof pixel error at the noise level (pixels²)."""
    return chi2_quantile(0.99, 2) * PIXEL_NOISE ** 2


def held_at_truth(problem: BALProblem, truth: BALProblem) -> BALProblem:
    """``problem`` with the held cameras :data:`FIXED` at their values in ``truth``."""
    cameras = np.array(problem.cameras, np.float64)
    cameras[list(FIXED)] = np.asarray(truth.cameras)[list(FIXED)]
    return dataclasses.replace(problem, cameras=cameras)


def corrupt_observations(problem: BALProblem, rate: float, seed: int) -> tuple[BALProblem,
                                                                                np.ndarray]:
    """``problem`` with ``rate`` of its observations (seeded choice) moved by a uniform
    offset in ±``OUTLIER_PX`` per coordinate; returns it and the outliers' indices."""
    rng = np.random.default_rng(seed)
    m = problem.observations.shape[0]
    bad = np.sort(rng.choice(m, size=int(round(rate * m)), replace=False))
    obs = np.array(problem.observations, np.float64)
    obs[bad] += rng.uniform(-OUTLIER_PX, OUTLIER_PX, size=(bad.size, 2))
    return dataclasses.replace(problem, observations=obs), bad


def _solve_options(max_steps: int) -> dict[str, Any]:
    # optimize_bal's defaults, a tight stopping rule and Schur elimination
    return dict(linear_solver="schur", damping="diagonal", strategy=Nielsen(1e-4),
                stopping=lw.stopping(max_steps))


def squared_errors(problem: BALProblem, variables: Any) -> np.ndarray:
    """(m,) squared reprojection errors ``|r|²`` (pixels²) at ``variables``."""
    r = factor_residuals(jg.bundle_adjustment_problem(problem).factors[0], variables)
    return np.asarray(jnp.sum(r * r, -1))


def observation_features(problem: BALProblem, variables: Any, kernel: Any) -> np.ndarray:
    """(m, 4) inputs of every observation at ``variables``: the three features of the
    module docstring and the kernel's weight ρ'(s)."""
    tau = threshold()
    s = squared_errors(problem, variables)
    pts = np.asarray(problem.point_index)
    order = np.argsort(pts, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(pts[order]) != 0])
    median = np.empty_like(s)
    for a, b in zip(starts, np.r_[starts[1:], s.size], strict=True):
        idx = order[a:b]
        for i in idx:  # the median of the point's other observations
            others = s[idx[idx != i]]
            median[i] = np.median(others) if others.size else tau
    rho1 = np.asarray(kernel.derivative(jnp.asarray(s)))
    return np.stack([np.log1p(s / tau), tau / (s + tau), np.log1p(s / (median + tau)), rho1],
                    1)


@dataclasses.dataclass
class Draw:
    """One corrupted problem: its outliers and its compiled solves."""

    problem: BALProblem
    outliers: np.ndarray
    max_steps: int
    _compiled: dict = dataclasses.field(default_factory=dict)
    _solved: dict = dataclasses.field(default_factory=dict)

    def graph(self, kernel: Any = None) -> Any:
        return jg.bundle_adjustment_problem(self.problem, kernel=kernel, fixed_cameras=FIXED)

    def kernel_solve(self, name: str, delta: float) -> Any:
        """Variables solved with kernel ``name`` of scale ``delta`` (one compilation per
        kernel, one solve per scale)."""
        if name not in self._compiled:
            kind, opts = KERNELS[name], _solve_options(self.max_steps)

            def run(d: Any) -> Any:
                return jg.solve(self.graph(kind(d)), **opts).variables

            self._compiled[name] = jax.jit(run)
        key = (name, float(delta))
        if key not in self._solved:
            self._solved[key] = self._compiled[name](jnp.asarray(delta, float))
        return self._solved[key]

    def weighted_solve(self, base: Any) -> Any:
        """``f(weights) -> points (n, 3)``: the problem with its observations weighted by
        (m,) ``weights``, solved from the variables ``base`` (differentiable in the
        weights)."""
        graph = eqx.tree_at(lambda g: g.variables, self.graph(), dict(base))
        opts = _solve_options(self.max_steps)

        def run(w: Any) -> Any:
            return jg.solve(jg.weighted_graph(graph, (w,)), **opts).variables["point"]

        return run

    def true_observations(self) -> np.ndarray:
        """(m,) oracle weights: 1 for the draw's true observations, 0 for its outliers."""
        return (~np.isin(np.arange(self.problem.observations.shape[0]),
                         self.outliers)).astype(float)

    def oracle_solution(self, base: Any) -> np.ndarray:
        """The draw's points with its outliers removed (weight 0), solved from ``base``."""
        return np.asarray(jax.jit(self.weighted_solve(base))(
            jnp.asarray(self.true_observations())))


def make_draws(clean: BALProblem, rate: float, seeds: Any, max_steps: int) -> list:
    out = []
    for seed in seeds:
        bad, outliers = corrupt_observations(clean, rate, int(seed))
        out.append(Draw(bad, outliers, max_steps))
    return out


def rmse(points: Any, ref: Any) -> float:
    d = np.asarray(points) - np.asarray(ref)
    return float(np.sqrt(np.mean(np.sum(d * d, -1))))


def tune_kernels(draws: list, ref: np.ndarray, scales: Any = SCALES,
                 kernels: Any = tuple(KERNELS)) -> dict[str, tuple]:
    """Per kernel: (best scale δ, mean points RMSE over ``draws`` at that δ)."""
    return lw.best_scales(kernels, scales, np.sqrt(threshold()), lambda name, delta: np.mean(
        [rmse(d.kernel_solve(name, delta)["point"], ref) for d in draws]))


def experiment(n_cameras: int = 10, n_points: int = 200, obs_per_point: int = 4,
               rate: float = 0.2, train_seeds: Any = (1, 2), test_seeds: Any = (101, 102), *,
               steps: int = 40, max_steps: int = 200, lr: float = 3e-2, seed: int = 0,
               scales: Any = SCALES, kernels: Any = tuple(KERNELS)) -> dict[str, Any]:
    """Tune the kernels and train the weights on ``train_seeds`` draws; points RMSE on
    ``test_seeds`` draws (held out) against the uncorrupted problem's solution for each
    tuned kernel, the untrained and the trained network, and the oracle weighting."""
    clean = held_at_truth(*synthetic_bal(n_cameras, n_points, obs_per_point, PIXEL_NOISE,
                                         seed=seed))
    ref = np.asarray(jg.solve(jg.bundle_adjustment_problem(clean, fixed_cameras=FIXED),
                              **_solve_options(max_steps)).variables["point"])
    train_draws = make_draws(clean, rate, train_seeds, max_steps)
    test_draws = make_draws(clean, rate, test_seeds, max_steps)
    tuned = tune_kernels(train_draws, ref, scales, kernels)
    best = min(tuned, key=lambda k: tuned[k][1])
    delta = tuned[best][0]
    kernel = KERNELS[best](delta)
    net0 = lw.WeightNet(jax.random.PRNGKey(seed), features=N_FEATURES)

    def loss_of(draw: Draw) -> Any:
        base = draw.kernel_solve(best, delta)
        feats = jnp.asarray(observation_features(draw.problem, base, kernel))
        solve, target = draw.weighted_solve(base), jnp.asarray(draw.oracle_solution(base))
        return lambda net: jnp.mean(jnp.sum((solve(net(feats)) - target) ** 2, -1))

    fit = lw.fit(net0, [loss_of(d) for d in train_draws], steps, lr)
    test = {name: [rmse(d.kernel_solve(name, tuned[name][0])["point"], ref) for d in test_draws]
            for name in kernels}
    runs = {"untrained": [], "learned": [], "oracle": []}
    for d in test_draws:
        base = d.kernel_solve(best, delta)
        feats = jnp.asarray(observation_features(d.problem, base, kernel))
        solve = jax.jit(d.weighted_solve(base))
        for name, w in (("untrained", net0(feats)), ("learned", fit.net(feats)),
                        ("oracle", jnp.asarray(d.true_observations()))):
            runs[name].append(rmse(solve(w), ref))
    test.update(runs)
    return dict(rate=rate, tuned=tuned, best=best, kernel=kernel, fit=fit, test=test)


def report(result: dict[str, Any]) -> str:
    """One line per contestant: held-out points RMSE (mean over the draws)."""
    lines = [f"outliers {result['rate']:.0%}: held-out points RMSE (scene units)"]
    for name, errs in result["test"].items():
        tuned = f" (δ = {result['tuned'][name][0]:.2f} px)" if name in result["tuned"] else ""
        lines.append(f"  {name:14s} {np.mean(errs):10.5f}{tuned}")
    return "\n".join(lines)
