"""Navigation state (rotation, velocity, position) of an IMU body."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from ..lie import SE3, SO3

Array = jax.Array


class NavState(eqx.Module):
    """``rot``: body-to-navigation rotation R (*b); ``vel``, ``pos``: velocity and
    position of the body in the navigation frame (*b, 3), the same batch shape *b."""

    rot: SO3
    vel: Array
    pos: Array

    def __init__(self, rot: Any, vel: Any, pos: Any):
        if not isinstance(rot, SO3):
            raise TypeError(f"NavState(rot): expected SO3, got {type(rot).__name__}")
        v, p = jnp.asarray(vel), jnp.asarray(pos)
        for arr, name in ((v, "vel"), (p, "pos")):
            if arr.ndim == 0 or arr.shape[-1] != 3:
                raise ValueError(f"NavState({name}): expected shape (..., 3), got "
                                 f"{tuple(arr.shape)}")
            if arr.shape[:-1] != rot.shape:  # a broadcast part breaks indexing and pose()
                raise ValueError(f"NavState({name}): expected batch shape {rot.shape} (rot's), "
                                 f"got {tuple(arr.shape)}; broadcast it first")
        self.rot, self.vel, self.pos = rot, v, p

    @classmethod
    def identity(cls, shape: Sequence[int] = (), dtype: Any = None) -> NavState:
        """Identity rotation, zero velocity and position."""
        dtype = jnp.result_type(float) if dtype is None else dtype
        z = jnp.zeros((*tuple(shape), 3), dtype)
        return cls(SO3.identity(shape, dtype), z, z)

    @property
    def shape(self) -> tuple[int, ...]:
        """Batch shape of the state."""
        return self.rot.shape

    def __getitem__(self, idx: Any) -> NavState:
        return NavState(self.rot[idx], self.vel[idx], self.pos[idx])

    def pose(self) -> SE3:
        """The pose ``[p, q]`` as :class:`~jaxpose.lie.SE3`."""
        return SE3(jnp.concatenate([self.pos, self.rot.data], -1))

    @classmethod
    def from_pose(cls, pose: SE3, vel: Any) -> NavState:
        """From an :class:`~jaxpose.lie.SE3` pose ``[p, q]`` (*b) and velocity (*b, 3)."""
        if not isinstance(pose, SE3):
            raise TypeError(f"NavState.from_pose(pose): expected SE3, got {type(pose).__name__}")
        return cls(SO3(pose.data[..., 3:7]), vel, pose.data[..., 0:3])
