"""The result of :func:`~jaxpose.optim.least_squares`."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax

from ..results import Results

Array = jax.Array


class Solution(eqx.Module):
    """Outcome of a least-squares solve (one per problem under ``vmap``).

    * ``params``: the best estimate found (lowest cost seen; never a rejected or
      non-finite trial), same pytree structure and types as the initial params;
    * ``status``: int32, a :class:`~jaxpose.Results` code (CONVERGED, MAX_STEPS, DIVERGED,
      NON_FINITE);
    * ``num_steps``: iterations (trial steps) taken; ``num_accepted``: accepted ones;
    * ``cost`` / ``initial_cost``: ``0.5 · Σ ρ(rᵀ W r)`` at ``params`` / at the start;
    * ``grad_norm``: ‖g‖_∞ of the tangent gradient at the last accepted estimate;
    * ``history``: cost after every iteration, shape (budget + 1,), entry 0 the initial
      cost, NaN past ``num_steps``; ``None`` unless ``history=True``.
    """

    params: Any
    status: Array
    num_steps: Array
    num_accepted: Array
    cost: Array
    initial_cost: Array
    grad_norm: Array
    history: Array | None = None

    @property
    def converged(self) -> Array:
        """Boolean array: ``status == Results.CONVERGED``."""
        return self.status == Results.CONVERGED

    @property
    def status_name(self) -> Any:
        """``status`` as text (``"converged"``, ...; an array of names when batched), by
        :meth:`jaxpose.Results.name_of`."""
        return Results.name_of(self.status)


__all__ = ["Solution"]
