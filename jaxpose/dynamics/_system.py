"""Discrete-time systems: ``x_{t+1} = f(x_t, u_t, t)``, ``y_t = h(x_t, u_t, t)``.

Conventions
-----------
* States ``x`` have shape ``(n,)``, inputs ``u`` ``(m,)``, observations ``y`` ``(p,)``;
  leading batch axes are handled by :func:`jax.vmap` (``linearize`` and :func:`rollout`
  do it for you when given batched arrays).
* ``t`` is the discrete step index (an int or scalar array). Continuous-time models
  (:mod:`jaxpose.dynamics._integrators`) convert it to time ``t·dt``.
* ``system(x, u, t)`` returns ``(f(x, u, t), h(x, u, t))`` — next state and the
  observation of the current state, as PyPose's ``System.forward``.
* Linearisation (PyPose's ``set_refpoint``) at ``(x*, u*)``:
  ``f(x, u) ≈ A x + B u + c1``, ``h(x, u) ≈ C x + D u + c2`` with the Jacobians taken
  per batch element by :func:`jax.jacfwd`.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_count
from .._dtypes import keep_dtypes
from ._checks import as_array, check_last, start_step, step_index, step_window

Array = jax.Array


class _Affine(eqx.Module):
    """The terms of an affine model ``x⁺ = A x + B u + c1``, ``y = C x + D u + c2``."""

    A: Array
    B: Array
    C: Array
    D: Array
    c1: Array
    c2: Array


class LinearizedSystem(_Affine):
    """A system linearised at a reference point (:meth:`System.linearize`): the affine
    model ``x⁺ ≈ A x + B u + c1``, ``y ≈ C x + D u + c2`` (shapes for one element;
    batches lead).

    ``A`` (n, n), ``B`` (n, m), ``C`` (p, n), ``D`` (p, m), ``c1`` (n,), ``c2`` (p,)."""


class System(eqx.Module):
    """Base class: subclass and implement :meth:`state_transition` (and
    :meth:`observation`, default ``y = x``). Array fields are parameters, so the model
    is differentiable with respect to them by ``jax.grad`` / ``eqx.filter_grad``."""

    is_linear: ClassVar[bool] = False

    @abc.abstractmethod
    def state_transition(self, x: Array, u: Array, t: Any = 0) -> Array:
        """Next state ``f(x, u, t)`` for one element: (n,), (m,) → (n,)."""

    def observation(self, x: Array, u: Array, t: Any = 0) -> Array:
        """Observation ``h(x, u, t)`` of the current state (default: the state)."""
        return x

    def __call__(self, x: Array, u: Array, t: Any = 0) -> tuple[Array, Array]:
        """``(f(x, u, t), h(x, u, t))``."""
        return self.state_transition(x, u, t), self.observation(x, u, t)

    def linearize(self, x: Array, u: Array, t: Any = 0) -> LinearizedSystem:
        """Jacobians at ``(x, u, t)``; batched inputs (..., n), (..., m) are linearised
        element by element (``vmap(jacfwd)``), giving (..., n, n) etc."""
        x = as_array(x, "x")
        u = as_array(u, "u")
        if x.ndim == 0 or u.ndim == 0:
            raise ValueError(
                f"linearize: expected x (..., n) and u (..., m), got {x.shape} and {u.shape}"
            )
        t = jnp.asarray(t)
        if x.ndim == 1 and u.ndim == 1 and t.ndim == 0:
            return self._linearize_one(x, u, t)
        batch = np.broadcast_shapes(x.shape[:-1], u.shape[:-1], t.shape)
        xb = jnp.broadcast_to(x, (*batch, x.shape[-1])).reshape(-1, x.shape[-1])
        ub = jnp.broadcast_to(u, (*batch, u.shape[-1])).reshape(-1, u.shape[-1])
        tb = jnp.broadcast_to(t, batch).reshape(-1)
        lin = jax.vmap(self._linearize_one)(xb, ub, tb)
        return jax.tree.map(lambda a: a.reshape(*batch, *a.shape[1:]), lin)

    def _linearize_one(self, x: Array, u: Array, t: Any) -> LinearizedSystem:
        f = lambda x_, u_: self.state_transition(x_, u_, t)
        h = lambda x_, u_: self.observation(x_, u_, t)
        fx, (A, B) = f(x, u), jax.jacfwd(f, argnums=(0, 1))(x, u)
        hx, (C, D) = h(x, u), jax.jacfwd(h, argnums=(0, 1))(x, u)
        c1 = fx - A @ x - B @ u
        c2 = hx - C @ x - D @ u
        return LinearizedSystem(A, B, C, D, c1, c2)


class NLS(System):
    """Nonlinear system. Subclass it, store parameters as array fields and implement
    ``state_transition`` / ``observation`` for one element; :meth:`linearize` gives
    per-element Jacobians by ``jacfwd`` and everything is differentiable w.r.t. the
    parameters. Example::

        class Pendulum(NLS):
            length: jax.Array
            def state_transition(self, x, u, t=0):
                th, om = x
                return jnp.stack([th + 0.05 * om,
                                  om + 0.05 * (-9.81 / self.length * jnp.sin(th) + u[0])])
    """


def _opt(x: Any, default: Array, name: str) -> Array:
    return default if x is None else as_array(x, name)


def _shape(*dims: Any) -> str:
    return f"({', '.join(map(str, dims))}{',' if len(dims) == 1 else ''})"


def _output_terms(
    A: Array, lead: tuple[int, ...], n: int, m: int, C: Any, D: Any, c1: Any, c2: Any
) -> tuple[Array, Array, Array, Array]:
    """``(C, D, c1, c2)`` of an :class:`LTI` (``lead = ()``) or :class:`LTV` (``lead =
    (T,)``), the defaults filled in (C = I, the others 0) and the shapes checked: C
    (*lead, p, n), D (*lead, p, m), c1 (*lead, n), c2 (*lead, p)."""
    notes = ("", "") if lead else (" (p observations, n = A.shape[0])", " (C rows, B columns)")
    C = _opt(C, jnp.broadcast_to(jnp.eye(n, dtype=A.dtype), (*lead, n, n)), "C")
    if C.ndim != len(lead) + 2 or C.shape[: len(lead)] != lead or C.shape[-1] != n:
        raise ValueError(f"C: expected shape {_shape(*lead, 'p', n)}{notes[0]}, got {C.shape}")
    p = C.shape[-2]
    checked = []
    for x, name, shape, note in (
        (D, "D", (*lead, p, m), notes[1]),
        (c1, "c1", (*lead, n), ""),
        (c2, "c2", (*lead, p), ""),
    ):
        x = _opt(x, jnp.zeros(shape, A.dtype), name)
        if x.shape != shape:
            raise ValueError(f"{name}: expected shape {_shape(*shape)}{note}, got {x.shape}")
        checked.append(x)
    return C, *checked


class _Linear(_Affine, System):
    """Shared by :class:`LTI` and :class:`LTV`: the affine terms (fields), their sizes
    and the affine maps; ``_at(t)`` gives ``(A, B, C, D, c1, c2)`` of step ``t``."""

    is_linear: ClassVar[bool] = True

    @property
    def state_dim(self) -> int:
        """State size n (``A.shape[-1]``)."""
        return self.A.shape[-1]

    @property
    def input_dim(self) -> int:
        """Input size m (``B.shape[-1]``)."""
        return self.B.shape[-1]

    @abc.abstractmethod
    def _at(self, t: Any) -> tuple[Array, ...]:
        """``(A, B, C, D, c1, c2)`` at step ``t``."""

    def _check_sizes(self, x: Array, u: Array) -> None:
        check_last(x, self.A.shape[-1], "x", "state size n = A.shape[-1]")
        check_last(u, self.B.shape[-1], "u", "input size m = B.shape[-1]")

    def state_transition(self, x: Array, u: Array, t: Any = 0) -> Array:
        self._check_sizes(x, u)
        A, B, _, _, c1, _ = self._at(t)
        return _mv(A, x) + _mv(B, u) + c1

    def observation(self, x: Array, u: Array, t: Any = 0) -> Array:
        check_last(x, self.C.shape[-1], "x", "state size n = C.shape[-1]")
        check_last(u, self.D.shape[-1], "u", "input size m = D.shape[-1]")
        _, _, C, D, _, c2 = self._at(t)
        return _mv(C, x) + _mv(D, u) + c2


class LTI(_Linear):
    """Linear time-invariant system ``x⁺ = A x + B u + c1``, ``y = C x + D u + c2``.

    ``A`` (n, n), ``B`` (n, m); optional ``C`` (p, n) (default I), ``D`` (p, m) (default
    0), ``c1`` (n,), ``c2`` (p,) (default 0). For a batch of systems, ``jax.vmap`` over a
    module built from batched matrices."""

    def __init__(
        self, A: Any, B: Any, C: Any = None, D: Any = None, c1: Any = None, c2: Any = None
    ):
        A = as_array(A, "A", 2)
        B = as_array(B, "B", 2)
        n, m = _check_ab(A, B, "A", "B")
        self.A, self.B = A, B
        self.C, self.D, self.c1, self.c2 = _output_terms(A, (), n, m, C, D, c1, c2)

    def _at(self, t: Any) -> tuple[Array, ...]:
        return self.A, self.B, self.C, self.D, self.c1, self.c2

    def linearize(self, x: Array, u: Array, t: Any = 0) -> LinearizedSystem:
        x, u = jnp.asarray(x), jnp.asarray(u)
        self._check_sizes(x, u)
        batch = np.broadcast_shapes(x.shape[:-1], u.shape[:-1], jnp.shape(t))
        return LinearizedSystem(*(jnp.broadcast_to(a, (*batch, *a.shape)) for a in self._at(t)))

    def matrices(self, horizon: int, t0: Any = 0) -> tuple[Array, Array]:
        """``(F, f)`` stacked over the horizon: F (T, n, n+m) = [A B], f (T, n) = c1
        (the same at every step ``t0`` … ``t0 + T − 1``)."""
        horizon = check_count(horizon, "horizon")
        start_step(t0)
        F = jnp.concatenate([self.A, self.B], -1)
        return (
            jnp.broadcast_to(F, (horizon, *F.shape)),
            jnp.broadcast_to(self.c1, (horizon, *self.c1.shape)),
        )


class LTV(_Linear):
    """Linear time-varying system: the matrices of :class:`LTI` with a leading time axis
    ``T``: ``A`` (T, n, n), ``B`` (T, n, m), ``C`` (T, p, n), ``D`` (T, p, m), ``c1``
    (T, n), ``c2`` (T, p). ``t`` selects the step, an integer in 0 … T − 1: any other
    ``t`` raises (``ValueError``, or ``eqx.error_if`` under ``jit``) instead of wrapping,
    truncating or clamping to the last step."""

    def __init__(
        self, A: Any, B: Any, C: Any = None, D: Any = None, c1: Any = None, c2: Any = None
    ):
        A = as_array(A, "A", 3)
        B = as_array(B, "B", 3)
        T = A.shape[0]
        if B.shape[0] != T:
            raise ValueError(f"B: expected {T} time steps (A.shape[0]), got shape {tuple(B.shape)}")
        n, m = _check_ab(A[0], B[0], "A", "B")
        self.A, self.B = A, B
        self.C, self.D, self.c1, self.c2 = _output_terms(A, (T,), n, m, C, D, c1, c2)

    @property
    def horizon(self) -> int:
        """Number of time steps T covered by the stacked matrices (``A.shape[0]``)."""
        return self.A.shape[0]

    def _at(self, t: Any) -> tuple[Array, ...]:
        t = step_index(t, steps=self.horizon, whose="LTV system's")
        return self.A[t], self.B[t], self.C[t], self.D[t], self.c1[t], self.c2[t]

    def linearize(self, x: Array, u: Array, t: Any = 0) -> LinearizedSystem:
        x, u, t = jnp.asarray(x), jnp.asarray(u), jnp.asarray(t)
        self._check_sizes(x, u)
        batch = np.broadcast_shapes(x.shape[:-1], u.shape[:-1], t.shape)
        return LinearizedSystem(*self._at(jnp.broadcast_to(t, batch)))

    def matrices(self, horizon: int, t0: Any = 0) -> tuple[Array, Array]:
        """``(F, f)`` for the ``horizon`` steps ``t0`` … ``t0 + T − 1``: F (T, n, n+m),
        f (T, n). ``t0`` may be traced; steps outside the system's raise (never clamp)."""
        horizon = check_count(horizon, "horizon")  # a negative one sliced arr[t0:-2]
        t0 = start_step(t0)
        F = jnp.concatenate([self.A, self.B], -1)
        return (step_window(F, t0, horizon, "LTV system's"),
                step_window(self.c1, t0, horizon, "LTV system's"))


def _check_ab(A: Array, B: Array, an: str, bn: str) -> tuple[int, int]:
    if A.shape[-1] != A.shape[-2]:
        raise ValueError(f"{an}: expected a square state matrix (n, n), got {tuple(A.shape)}")
    if B.shape[-2] != A.shape[-1]:
        raise ValueError(
            f"{bn}: expected shape ({A.shape[-1]}, m) to match {an} ({A.shape[-1]} states), "
            f"got {tuple(B.shape)}"
        )
    return A.shape[-1], B.shape[-1]


def _mv(M: Array, v: Array) -> Array:
    return jnp.einsum("...ij,...j->...i", M, v)


# ----------------------------------------------------------------------------------
# Rollouts
# ----------------------------------------------------------------------------------
def rollout(system: System, x0: Any, us: Any, t0: Any = 0) -> tuple[Array, Array]:
    """Simulate ``system`` from ``x0`` under inputs ``us`` with ``lax.scan``.

    ``x0`` (n,) or a group element, ``us`` (T, m) → ``xs`` (T+1, n) (``x0`` first),
    ``ys`` (T, p) with ``ys[t] = h(xs[t], us[t], t0 + t)``. Batched arrays ``x0``
    (..., n) and/or ``us`` (..., T, m) are broadcast and vmapped."""
    us = as_array(us, "us")
    if us.ndim < 2:
        raise ValueError(f"us: expected inputs of shape (T, m), got {tuple(us.shape)}")
    if isinstance(x0, eqx.Module):
        if x0.shape != () or us.ndim != 2:  # type: ignore[attr-defined]
            return eqx.filter_vmap(lambda a, b: rollout(system, a, b, t0))(x0, us)
        return _rollout_one(system, x0, us, t0)
    x0 = as_array(x0, "x0")
    if x0.ndim == 0:
        raise ValueError("x0: expected a state vector (n,), got a scalar")
    if x0.ndim == 1 and us.ndim == 2:
        return _rollout_one(system, x0, us, t0)
    batch = np.broadcast_shapes(x0.shape[:-1], us.shape[:-2])
    xb = jnp.broadcast_to(x0, (*batch, x0.shape[-1])).reshape(-1, x0.shape[-1])
    ub = jnp.broadcast_to(us, (*batch, *us.shape[-2:])).reshape(-1, *us.shape[-2:])
    xs, ys = jax.vmap(lambda a, b: _rollout_one(system, a, b, t0))(xb, ub)
    return xs.reshape(*batch, *xs.shape[1:]), ys.reshape(*batch, *ys.shape[1:])


def _rollout_one(system: System, x0: Any, us: Array, t0: Any) -> tuple[Any, Array]:
    T = us.shape[0]
    ts = jnp.asarray(t0) + jnp.arange(T)

    def step(x: Any, ut: tuple[Array, Array]) -> tuple[Any, tuple[Any, Array]]:
        u, t = ut
        x_next, y = system(x, u, t)
        x_next = keep_dtypes(x_next, x)  # float64 model data: the state keeps x0's dtype
        return x_next, (x_next, y)

    _, (xs, ys) = jax.lax.scan(step, x0, (us, ts))
    xs = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b], 0), x0, xs)
    return xs, ys
