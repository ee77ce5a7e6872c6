"""Factors: residual functions over a few variables, evaluated in groups with ``vmap``.

A :class:`Factor` describes *m* factors of one type at once: a residual function written
for a single factor, the variables each factor touches (a variable-type name and an
index array of length m per slot), per-factor data (a pytree with leading axis m, e.g.
the measurements), and an information matrix per factor (or one shared).

Cost convention: ``0.5 · Σ ρ(rᵀ Ω r)`` over factors, with ρ the identity unless a robust
kernel is given. Whitening uses the upper Cholesky factor S of Ω (Ω = SᵀS): r̃ = S r.
Robust kernels are :class:`jaxpose.optim.Kernel` objects (plain callables ρ(s) are wrapped,
their derivatives taken by autodiff) and are folded into the least-squares blocks by a
:class:`jaxpose.optim.Corrector` (default :class:`~jaxpose.optim.FastTriggs`, i.e. IRLS).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _small_linalg as small_linalg
from ..lie._base import LieGroup, small_matmul
from ..optim._correctors import Corrector, FastTriggs
from ..optim._kernels import Kernel

Array = jax.Array


class CallableKernel(Kernel):
    """A plain scalar callable ρ(s) as a :class:`~jaxpose.optim.Kernel` (applied
    elementwise; derivatives by autodiff)."""

    fn: Callable[[Array], Array] = eqx.field(static=True)

    def __call__(self, s: Array) -> Array:
        return jnp.vectorize(self.fn)(s)

    def derivative(self, s: Array) -> Array:
        return jnp.vectorize(jax.grad(self.fn))(s)

    def second_derivative(self, s: Array) -> Array:
        return jnp.vectorize(jax.grad(jax.grad(self.fn)))(s)


def as_kernel(kernel: Any, where: str = "Factor(kernel)") -> Kernel | None:
    """None, a :class:`~jaxpose.optim.Kernel`, or a callable ρ(s) wrapped as one."""
    if kernel is None or isinstance(kernel, Kernel):
        return kernel
    if not callable(kernel):
        raise TypeError(f"{where}: expected a jaxpose.optim Kernel or a callable ρ(s), got "
                        f"{type(kernel).__name__}")
    return CallableKernel(kernel)


class Factor(eqx.Module):
    """A group of *m* factors of the same type.

    Args:
        residual: ``residual(*variables, data) -> (r,)`` for ONE factor (vmapped here).
            Each variable is a group element (unbatched) or an array of shape (d,).
        variables: one ``(type_name, indices)`` pair per slot; ``indices`` has shape (m,).
        data: pytree with leading axis m passed to ``residual`` (or None).
        information: (m, r, r), (r, r) or None (identity); symmetric positive definite.
        kernel: optional robust kernel ρ(s) of the squared whitened norm s = |r̃|²
            (a :class:`jaxpose.optim.Kernel`, e.g. ``Huber(1.0)``, or any callable).
        corrector: how the kernel enters the Gauss–Newton blocks: a
            :class:`jaxpose.optim.Corrector` (default ``FastTriggs()``: rows scaled by
            √ρ'(s); ``Triggs()`` adds the ρ'' curvature term).
        jacobian: optional analytic Jacobian ``jacobian(*variables, data) -> (r, J_1, …)``
            for ONE factor, J_s of shape (r, tangent_dim_s) with respect to the right
            perturbation X_s ⊕ δ_s. Default: :func:`between_jacobian` for
            :func:`between_residual` (smaller, faster programs than autodiff), else
            forward-mode autodiff of ``residual``.
        name: label used in messages and progress output.
    """

    residual: Callable[..., Array] = eqx.field(static=True)
    slots: tuple[str, ...] = eqx.field(static=True)
    indices: tuple[Array, ...]
    data: Any
    sqrt_info: Array | None
    kernel: Kernel | None  # a pytree: array parameters are traced and differentiable
    corrector: Corrector = eqx.field(static=True)
    jacobian: Callable[..., Any] | None = eqx.field(static=True)
    name: str = eqx.field(static=True)
    count: int = eqx.field(static=True)

    def __init__(
        self,
        residual: Callable[..., Array],
        variables: Sequence[tuple[str, Any]],
        data: Any = None,
        information: Any = None,
        kernel: Callable[[Array], Array] | None = None,
        name: str | None = None,
        jacobian: Callable[..., Any] | None = None,
        corrector: Corrector | None = None,
    ):
        if not callable(residual):
            raise TypeError(f"Factor(residual): expected a callable, got {type(residual).__name__}")
        if not variables:
            raise ValueError("Factor(variables): expected at least one (type_name, indices) slot")
        slots, idx = [], []
        count = None
        for k, slot in enumerate(variables):
            if not (isinstance(slot, tuple) and len(slot) == 2 and isinstance(slot[0], str)):
                raise TypeError(
                    f"Factor(variables[{k}]): expected a (type_name, indices) pair, got {slot!r}"
                )
            if isinstance(slot[1], jax.core.Tracer):
                raise TypeError(
                    f"Factor(variables[{k}]): indices must be concrete (numpy or Python "
                    f"ints), not traced: a graph's structure is static; trace its data "
                    f"and information instead"
                )
            ind = np.asarray(slot[1])
            if ind.ndim != 1 or not np.issubdtype(ind.dtype, np.integer):
                raise ValueError(
                    f"Factor(variables[{k}]): indices must be a 1-D integer array, "
                    f"got shape {ind.shape} dtype {ind.dtype}"
                )
            if count is None:
                count = ind.shape[0]
            elif ind.shape[0] != count:
                raise ValueError(
                    f"Factor(variables[{k}]): {ind.shape[0]} indices, but slot 0 has {count}"
                )
            slots.append(slot[0])
            idx.append(np.asarray(ind, np.int32))  # static structure, concrete under jit
        assert count is not None
        for leaf in jax.tree.leaves(data, is_leaf=lambda x: isinstance(x, LieGroup)):
            lead = leaf.shape[0] if not isinstance(leaf, LieGroup) else (leaf.shape or (None,))[0]
            if lead != count:
                raise ValueError(
                    f"Factor(data): every leaf needs leading axis {count} (one per factor), "
                    f"got a leaf with shape {getattr(leaf, 'shape', None)}"
                )
        self.residual = residual
        self.slots = tuple(slots)
        self.indices = tuple(idx)
        self.data = data
        self.sqrt_info = None if information is None else _sqrt_information(information, count)
        self.kernel = as_kernel(kernel)
        if corrector is not None and not isinstance(corrector, Corrector):
            raise TypeError(
                f"Factor(corrector): expected a jaxpose.optim Corrector, got "
                f"{type(corrector).__name__}"
            )
        self.corrector = FastTriggs() if corrector is None else corrector
        if jacobian is not None and not callable(jacobian):
            raise TypeError(f"Factor(jacobian): expected a callable, got {type(jacobian).__name__}")
        if jacobian is None and residual is between_residual:
            jacobian = between_jacobian
        self.jacobian = jacobian
        self.name = name or getattr(residual, "__name__", "factor")
        self.count = int(count)


def _sqrt_information(information: Any, count: int) -> Array:
    """Upper Cholesky factor S (Ω = SᵀS), (m, r, r); rejects non-SPD matrices eagerly.

    Traced information (a Factor built inside ``jit``/``grad``, e.g. learned weights) is
    factorised with ``jnp`` (differentiable); a matrix that is not positive definite then
    raises at run time (``eqx.error_if``)."""
    if isinstance(information, jax.core.Tracer):
        return _traced_sqrt_information(information, count)
    om = np.asarray(information, dtype=np.float64)
    if om.ndim == 2:
        om = np.broadcast_to(om, (count, *om.shape))
    if om.ndim != 3 or om.shape[0] != count or om.shape[1] != om.shape[2]:
        raise ValueError(
            f"Factor(information): expected shape ({count}, r, r) or (r, r), got {om.shape}"
        )
    if not np.all(np.isfinite(om)):
        bad = int(np.argmax(~np.all(np.isfinite(om), axis=(1, 2))))
        raise ValueError(f"Factor(information): factor {bad} has a non-finite information matrix")
    if not np.allclose(om, np.swapaxes(om, 1, 2), rtol=1e-9, atol=1e-12):
        bad = int(np.argmax(~np.all(np.isclose(om, np.swapaxes(om, 1, 2)), axis=(1, 2))))
        raise ValueError(
            f"Factor(information): factor {bad} has a non-symmetric information matrix"
        )
    try:
        lower = np.linalg.cholesky(om)
    except np.linalg.LinAlgError:
        eig = np.linalg.eigvalsh(om).min(axis=1)
        bad = int(np.argmin(eig))
        raise ValueError(
            f"Factor(information): factor {bad} has an information matrix that is not "
            f"positive definite (smallest eigenvalue {eig[bad]:.3g})"
        ) from None
    return jnp.asarray(np.swapaxes(lower, 1, 2))


def _traced_sqrt_information(information: Array, count: int) -> Array:
    om = jnp.asarray(information)
    if om.ndim == 2:
        om = jnp.broadcast_to(om, (count, *om.shape))
    if om.ndim != 3 or om.shape[0] != count or om.shape[1] != om.shape[2]:
        raise ValueError(
            f"Factor(information): expected shape ({count}, r, r) or (r, r), got {om.shape}"
        )
    lower = small_linalg.cholesky(om)
    lower = eqx.error_if(
        lower,
        ~jnp.all(jnp.isfinite(lower)),
        "Factor(information): an information matrix is not positive definite (or not finite)",
    )
    return jnp.swapaxes(lower, 1, 2)


# ----------------------------------------------------------------------------------
# Common residuals (for one factor; vmapped by the graph)
# ----------------------------------------------------------------------------------
def between_residual(xi: LieGroup, xj: LieGroup, z: LieGroup) -> Array:
    """Relative-pose residual ``Log(Z⁻¹ · Xi⁻¹ · Xj)`` (g2o / GTSAM BetweenFactor)."""
    return z.inv().compose(xi.inv().compose(xj)).log().data


def between_jacobian(xi: LieGroup, xj: LieGroup, z: LieGroup) -> tuple[Array, Array, Array]:
    """Residual and analytic Jacobians of :func:`between_residual`.

    With E = Z⁻¹Xi⁻¹Xj and r = Log(E): ∂r/∂δj = Jr⁻¹(r) and ∂r/∂δi = −Jr⁻¹(r)·Adj(Xj⁻¹Xi)."""
    rel = xi.inv().compose(xj)
    r = z.inv().compose(rel).log()
    jr_inv = r.group._jl_inv_principal(-r.data)  # Jr⁻¹(r) = Jl⁻¹(−r), |r's angle| ≤ π
    return r.data, -small_matmul(jr_inv, rel.inv().adj_matrix()), jr_inv


def prior_residual(x: LieGroup, z: LieGroup) -> Array:
    """Prior residual ``Log(Z⁻¹ · X)``."""
    return z.inv().compose(x).log().data


def vector_prior_residual(x: Array, z: Array) -> Array:
    """Prior on a Euclidean variable: ``x − z``."""
    return x - z
