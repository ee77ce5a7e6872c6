"""MuJoCo MJX models as :class:`~jaxpose.dynamics.System` s.

:class:`MJXSystem` wraps an MJX model (``mujoco.mjx``, ``pip install jaxpose[mjx]``) so
that MuJoCo's physics supplies ``state_transition`` for jaxpose's filters (EKF/UKF/PF),
iLQR/MPC and rollouts, under ``jit``, ``vmap`` and ``grad``.

Conventions
-----------
* State ``x = [qpos (nq), qvel (nv), act (na)]``, shape ``(nq + nv + na,)``; input
  ``u = ctrl (nu,)``. Joint quaternions (ball/free joints) are plain coordinates of ``x``
  here, so EKF covariances and iLQR steps treat them as vectors: use models with hinge
  and slide joints for those, or renormalise.
* One System step is ``substeps`` calls of ``mjx.step`` (the model's integrator, timestep
  ``model.opt.timestep``), so ``dt = substeps · timestep``; ``data.time = t · dt``.
* ``y = observation(x, u, t)``: ``observe="state"`` (``x``), ``"qpos"`` or
  ``"sensordata"`` (the model's sensors after ``mjx.forward``).
* Learnable physics: ``params`` (any pytree of arrays) is applied to the MJX model by the
  static function ``bind(model, params) -> model`` at every step, e.g.
  ``lambda m, p: m.replace(dof_damping=p["damping"])``. Gradients w.r.t. ``params`` flow
  through MuJoCo's smooth dynamics; contacts and joint limits go through MJX's iterative
  constraint solver (a ``while_loop``), which supports forward-mode (``jacfwd``, EKF and
  iLQR linearisation) but not reverse-mode differentiation.

``mujoco`` is imported only when an MJX model is built (``from_xml``/``from_mujoco``), so
``import jaxpose`` never needs it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import count_field
from ._system import System

Array = jax.Array

OBSERVE = ("state", "qpos", "sensordata")
"""What :class:`MJXSystem` observes: the full state ``[qpos, qvel, act]``, ``qpos`` only,
or the model's sensor readings (``mjData.sensordata``)."""


def _mjx() -> Any:
    try:
        from mujoco import mjx
    except ImportError as err:  # pragma: no cover - exercised only without mujoco
        raise ImportError(
            "jaxpose.dynamics.mjx needs MuJoCo MJX: pip install 'jaxpose[mjx]' "
            f"(mujoco and mujoco-mjx) ({err})"
        ) from err
    return mjx


class MJXSystem(System):
    """A MuJoCo MJX model as a discrete-time system (see the module docstring).

    ``MJXSystem(model, data, params=None, bind=None, substeps=1, observe="state")``:
    ``model`` an ``mjx.Model``, ``data`` an ``mjx.Data`` template (e.g.
    ``mjx.make_data(model)``; its ``qpos``/``qvel``/``act``/``ctrl``/``time`` are
    overwritten at every step). Build from MJCF with :meth:`from_xml`."""

    model: Any
    data: Any
    params: Any = None
    bind: Callable[[Any, Any], Any] | None = eqx.field(static=True, default=None)
    substeps: int = count_field("substeps", default=1)
    observe: str = eqx.field(static=True, default="state")

    def __check_init__(self) -> None:
        if self.observe not in OBSERVE:
            raise ValueError(f"observe: expected one of {OBSERVE}, got {self.observe!r}")
        if self.params is not None and self.bind is None:
            raise ValueError("params: given without bind(model, params) to apply them")
        mjx = _mjx()
        if not isinstance(self.model, mjx.Model):
            raise TypeError(
                f"model: expected an mjx.Model (mjx.put_model), got {type(self.model).__name__}"
            )
        if not isinstance(self.data, mjx.Data):
            raise TypeError(
                f"data: expected an mjx.Data (mjx.make_data), got {type(self.data).__name__}"
            )

    @classmethod
    def from_mujoco(
        cls,
        mj_model: Any,
        *,
        params: Any = None,
        bind: Callable[[Any, Any], Any] | None = None,
        substeps: int = 1,
        observe: str = "state",
    ) -> MJXSystem:
        """From a ``mujoco.MjModel`` (``mjx.put_model``; float64 when x64 is enabled)."""
        mjx = _mjx()
        model = mjx.put_model(mj_model)
        return cls(model, mjx.make_data(model), params, bind, substeps, observe)

    @classmethod
    def from_xml(cls, xml: str, **kwargs: Any) -> MJXSystem:
        """From an MJCF string (keywords as :meth:`from_mujoco`)."""
        import mujoco

        return cls.from_mujoco(mujoco.MjModel.from_xml_string(xml), **kwargs)

    # ------------------------------------------------------------------ sizes
    @property
    def state_dim(self) -> int:
        """``nq + nv + na``."""
        return self.model.nq + self.model.nv + self.model.na

    @property
    def input_dim(self) -> int:
        """``nu``."""
        return self.model.nu

    @property
    def dt(self) -> Any:
        """Seconds per System step: ``substeps · model.opt.timestep``."""
        return self.substeps * self.model.opt.timestep

    # ------------------------------------------------------------------ physics
    def physics(self) -> Any:
        """The MJX model with ``params`` applied (``bind(model, params)``)."""
        if self.bind is None:
            return self.model
        return self.bind(self.model, self.params)

    def to_data(self, x: Array, u: Array, t: Any = 0) -> Any:
        """``mjx.Data`` holding state ``x`` (n,), control ``u`` (nu,) at step ``t``."""
        m = self.model
        n = self.state_dim
        if jnp.shape(x) != (n,):
            raise ValueError(
                f"x: expected shape ({n},) = (nq + nv + na,) = ({m.nq} + {m.nv} + {m.na},), "
                f"got {tuple(jnp.shape(x))}"
            )
        if jnp.shape(u) != (m.nu,):
            raise ValueError(
                f"u: expected shape ({m.nu},) (nu controls), got {tuple(jnp.shape(u))}"
            )
        dtype = self.data.qpos.dtype
        x = jnp.asarray(x, dtype)
        nq, nv = m.nq, m.nv
        return self.data.replace(
            qpos=x[:nq],
            qvel=x[nq : nq + nv],
            act=x[nq + nv :],
            ctrl=jnp.asarray(u, dtype),
            time=jnp.asarray(t, dtype) * self.dt,
        )

    @staticmethod
    def state_of(data: Any) -> Array:
        """``[qpos, qvel, act]`` of an ``mjx.Data``."""
        return jnp.concatenate([data.qpos, data.qvel, data.act])

    def state_transition(self, x: Array, u: Array, t: Any = 0) -> Array:
        """``substeps`` MJX steps from ``x`` under ``u`` (held constant)."""
        mjx = _mjx()
        m = self.physics()
        d = self.to_data(x, u, t)
        for _ in range(self.substeps):
            d = mjx.step(m, d)
        return self.state_of(d).astype(jnp.result_type(x))

    def observation(self, x: Array, u: Array, t: Any = 0) -> Array:
        """``x``, ``qpos`` or the model's ``sensordata`` (see ``observe``)."""
        if self.observe == "state":
            return x
        if self.observe == "qpos":
            return x[: self.model.nq]
        mjx = _mjx()
        d = mjx.forward(self.physics(), self.to_data(x, u, t))
        return d.sensordata.astype(jnp.result_type(x))


__all__ = ["OBSERVE", "MJXSystem"]
