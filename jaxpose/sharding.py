"""Scaling batched problems past one device with ``jax.sharding``.

Many jaxpose workloads are batches of independent problems: Lie-group ops over millions
of poses, ``vmap``-ed least-squares solves (each with its own damping and stopping),
filters over many sequences. Two ways to spread them over the devices of a 1-D mesh
(axis ``"batch"``):

* **Data placement** (:func:`shard_batch`): put the leading axis of every array in a
  pytree across the devices (``NamedSharding(mesh, P("batch"))``) and call any jitted
  function on it; XLA's partitioner keeps element-wise batched work on the device that
  holds the data. Best for straight-line code (Lie ops, losses).
* **Batched functions** (:func:`shard_vmap`): ``vmap(fn)`` over a batch split across
  the devices, padded when the batch is not a multiple of the device count; either
  partitioned by XLA (default, works for everything) or as explicit per-device
  programs with ``shard_map`` (no communication at all; see its ``method``).

Batch sizes that are not a multiple of the device count: :func:`shard_vmap` pads the
batch by repeating its last element (always a valid input — a zero quaternion would not
be) and drops the padded results (with ``"partition"`` this costs a reshuffle of the
outputs between devices; a multiple of the device count needs none); :func:`pad_batch`
does the same for :func:`shard_batch`.

Multi-GPU / TPU: the same code runs unchanged; ``batch_mesh()`` takes every device of the
default backend (``jax.devices()``); multi-host recipe in ``docs/sharding.md``. On CPU,
test with simulated devices by setting ``XLA_FLAGS=--xla_force_host_platform_device_count=4``
before JAX starts. CPU caveat (jaxlib 0.10.2): batched LAPACK kernels (Cholesky, LU, QR
under ``vmap``) split a large batch over XLA's intra-op thread pool and block a pool
thread while they wait; when as many simulated devices as cores do this at once, the
process deadlocks. Keep per-device LAPACK batches small on simulated devices or use a
LAPACK-free solver (``jaxpose.optim.CG``, ``graph.solve(linear_solver="pcg")``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ._checks import check_count

__all__ = [
    "batch_mesh",
    "batch_sharding",
    "pad_batch",
    "replicate",
    "shard_batch",
    "shard_vmap",
]

PyTree = Any


def _shard_map(fn: Callable, mesh: Mesh, in_specs: Any, out_specs: Any) -> Callable:
    """``jax.shard_map`` (jax ≥ 0.6) or the experimental one, replication checks off
    (the per-device programs are independent; nothing is claimed replicated)."""
    if hasattr(jax, "shard_map"):
        return jax.shard_map(
            fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False
        )
    from jax.experimental.shard_map import shard_map  # pragma: no cover - old jax

    return shard_map(  # pragma: no cover - old jax
        fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_rep=False
    )


def batch_mesh(devices: Sequence[Any] | int | None = None, axis_name: str = "batch") -> Mesh:
    """A 1-D :class:`~jax.sharding.Mesh` named ``axis_name`` over ``devices``: a list of
    devices, a count (the first ``n`` of ``jax.devices()``), or ``None`` (all of them)."""
    all_devices = jax.devices()
    if devices is None:
        devs = all_devices
    elif isinstance(devices, bool | str | bytes) or not isinstance(
            devices, int | np.integer | Sequence | np.ndarray):
        raise TypeError(f"batch_mesh(devices): expected a device count, a sequence of devices "
                        f"or None, got {type(devices).__name__} {devices!r}")
    elif isinstance(devices, int | np.integer):
        if not 1 <= int(devices) <= len(all_devices):
            raise ValueError(
                f"batch_mesh(devices): expected a device count in [1, {len(all_devices)}], "
                f"got {devices}"
            )
        devs = all_devices[: int(devices)]
    else:
        devs = list(devices)
        if not devs:
            raise ValueError("batch_mesh(devices): expected at least one device, got none")
        if not all(isinstance(d, jax.Device) for d in devs):
            raise TypeError(f"batch_mesh(devices): expected jax devices (jax.devices()), got "
                            f"{[type(d).__name__ for d in devs]}")
    return Mesh(np.asarray(devs), (axis_name,))


def _mesh_axis(mesh: Mesh | None, axis_name: str | None) -> tuple[Mesh, str]:
    if mesh is None:
        mesh = batch_mesh(axis_name=axis_name or "batch")
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh: expected a jax.sharding.Mesh, got {type(mesh).__name__}")
    axis = axis_name or mesh.axis_names[0]
    if axis not in mesh.axis_names:
        raise ValueError(f"axis_name: {axis!r} is not an axis of the mesh {mesh.axis_names}")
    return mesh, axis


def batch_sharding(mesh: Mesh | None = None, axis_name: str | None = None) -> NamedSharding:
    """``NamedSharding(mesh, P(axis_name))``: leading axis split across the mesh axis,
    the other axes whole on each device."""
    mesh, axis = _mesh_axis(mesh, axis_name)
    return NamedSharding(mesh, P(axis))


def _leaves_with_batch(tree: PyTree, what: str) -> tuple[list[Any], Any, int]:
    leaves, treedef = jax.tree.flatten(tree)
    if not leaves:
        raise ValueError(f"{what}: expected a pytree with at least one array, got none")
    sizes = set()
    for leaf in leaves:
        shape = np.shape(leaf)
        if len(shape) == 0:
            raise ValueError(
                f"{what}: every array needs a leading batch axis; got a scalar leaf "
                f"(replicate shared values with jaxpose.sharding.replicate)"
            )
        sizes.add(shape[0])
    if len(sizes) != 1:
        raise ValueError(f"{what}: leading axes disagree: sizes {sorted(sizes)}")
    return leaves, treedef, sizes.pop()


def pad_batch(tree: PyTree, multiple: int) -> tuple[PyTree, int]:
    """Pad the leading axis of every array in ``tree`` to a multiple of ``multiple`` by
    repeating the last element; returns ``(padded, n)`` with ``n`` the original size
    (results of the real elements: ``jax.tree.map(lambda x: x[:n], out)``)."""
    multiple = check_count(multiple, "pad_batch(multiple)")
    leaves, treedef, n = _leaves_with_batch(tree, "pad_batch(tree)")
    if n == 0:
        raise ValueError("pad_batch(tree): the batch is empty")
    extra = -n % multiple
    if extra == 0:
        return tree, n

    def pad(leaf: Any) -> Any:  # NumPy stays NumPy, as it does unpadded
        xp = np if isinstance(leaf, np.ndarray) else jnp
        return xp.concatenate([leaf, xp.repeat(xp.asarray(leaf)[-1:], extra, axis=0)], axis=0)

    padded = [pad(leaf) for leaf in leaves]
    return jax.tree.unflatten(treedef, padded), n


def shard_batch(
    tree: PyTree, mesh: Mesh | None = None, axis_name: str | None = None
) -> PyTree:
    """Place ``tree`` (arrays, jaxpose groups, any pytree) with the leading axis of every
    array split across the mesh (default: all devices). The leading sizes must agree and be
    a multiple of the device count (see :func:`pad_batch`). Returns the same pytree of
    sharded ``jax.Array`` s; jitted functions of it run where the data lives."""
    mesh, axis = _mesh_axis(mesh, axis_name)
    _, _, n = _leaves_with_batch(tree, "shard_batch(tree)")
    ndev = mesh.shape[axis]
    if n % ndev:
        raise ValueError(
            f"shard_batch(tree): the leading axis ({n}) is not a multiple of the "
            f"{ndev} devices on mesh axis {axis!r}; pad it with jaxpose.sharding.pad_batch"
        )
    return jax.device_put(tree, NamedSharding(mesh, P(axis)))


def replicate(tree: PyTree, mesh: Mesh | None = None) -> PyTree:
    """Place a full copy of ``tree`` on every device of ``mesh`` (shared parameters,
    models, measurement noise)."""
    mesh, _ = _mesh_axis(mesh, None)
    return jax.device_put(tree, NamedSharding(mesh, P()))


def _vmap_axes(in_axes: Any, nargs: int) -> tuple[int | None, ...]:
    """``in_axes`` as one entry per positional argument, each 0 or None (a Python or
    NumPy integer 0; a bool is refused), at least one 0."""
    axes = tuple(in_axes) if isinstance(in_axes, Sequence) else (in_axes,) * nargs
    if len(axes) != nargs:
        raise ValueError(f"shard_vmap(in_axes): {len(axes)} entries for {nargs} arguments")
    if not all(a is None or (isinstance(a, int | np.integer) and not isinstance(a, bool)
                             and a == 0) for a in axes):
        raise ValueError(f"shard_vmap(in_axes): entries must be 0 or None, got {axes}")
    if all(a is None for a in axes):
        raise ValueError("shard_vmap(in_axes): at least one argument must be batched (0)")
    return tuple(None if a is None else 0 for a in axes)


def shard_vmap(
    fn: Callable[..., Any],
    mesh: Mesh | None = None,
    *,
    in_axes: int | None | Sequence[int | None] = 0,
    axis_name: str | None = None,
    method: str = "partition",
) -> Callable[..., Any]:
    """``vmap(fn)`` over a batch split across the devices of ``mesh``, jitted; outputs are
    batch-sharded along their leading axis and equal ``jax.vmap(fn)(*args)``.

    ``in_axes`` per positional argument: ``0`` (batched along the leading axis of every
    leaf) or ``None`` (the same value for all, replicated). Batches that are not a multiple
    of the device count are padded with copies of the last element and the padding is
    removed from the outputs, which then come back replicated (a batch of 5 on 4 devices),
    not batch-sharded: same values, a different sharding.

    ``method``:

    * ``"partition"`` (default): ``jit(vmap(fn))`` with batch-sharded inputs and outputs;
      XLA's SPMD partitioner splits the work. Works for any ``fn``. A ``while_loop``
      under ``vmap`` (``least_squares``, iLQR) runs until the last problem of the whole
      batch is done, with one small all-reduce of the loop condition per iteration.
    * ``"shard_map"``: ``shard_map(vmap(fn))``: every device runs its own program on its
      slice with no communication (a device's loop stops when its own problems are done).
      Functions that call ``lineax`` (``jaxpose.optim.least_squares``) fail inside
      ``shard_map`` (and ``pmap``) with JAX 0.10 ("Vector and operator structures do not
      match", lineax issue #185); use ``"partition"`` for them (and for
      ``graph.solve(..., linear_solver="pcg")``). ``graph.solve`` with its other linear
      solvers, filters, Lie ops and control work with both.

      A host callback (``graph.solve(..., linear_solver="sparse")``: CHOLMOD) cannot be
      partitioned: under ``"partition"`` XLA gathers its operands (the whole batch's
      sparse systems) onto every device at every iteration; use ``"shard_map"``.

    The returned function is jitted and takes the arguments positionally; every argument
    is traced, so close over static values (shapes, strings, functions) in ``fn``. An
    empty batch gives ``jax.vmap``'s empty result. ``.lower(*args).compile()`` gives the
    compiled program (e.g. to inspect its collectives).
    """
    mesh, axis = _mesh_axis(mesh, axis_name)
    if method not in ("partition", "shard_map"):
        raise ValueError(f"shard_vmap(method): expected 'partition' or 'shard_map', got {method!r}")
    ndev = mesh.shape[axis]
    batch = NamedSharding(mesh, P(axis))

    @jax.jit
    def run(*args: Any, **kwargs: Any) -> Any:
        if kwargs:
            raise TypeError(f"shard_vmap: pass the arguments positionally (in_axes is per "
                            f"positional argument); got keyword arguments {sorted(kwargs)}")
        axes = _vmap_axes(in_axes, len(args))
        batched = [i for i, a in enumerate(axes) if a == 0]
        sizes = {i: _leaves_with_batch(args[i], f"shard_vmap(argument {i})")[2] for i in batched}
        if len(set(sizes.values())) > 1:
            raise ValueError(f"shard_vmap: the batched arguments' leading axes disagree "
                             f"(argument: size): {sizes}")
        if not sizes[batched[0]]:
            return jax.vmap(fn, in_axes=axes)(*args)
        padded, n = pad_batch(tuple(args[i] for i in batched), ndev)
        args = list(args)
        for i, x in zip(batched, padded):
            args[i] = jax.lax.with_sharding_constraint(x, batch)
        if method == "shard_map":
            specs = tuple(P(axis) if a == 0 else P() for a in axes)
            out = _shard_map(jax.vmap(fn, in_axes=axes), mesh, specs, P(axis))(*args)
        else:
            out = jax.lax.with_sharding_constraint(jax.vmap(fn, in_axes=axes)(*args), batch)
        return jax.tree.map(lambda x: x[:n], out) if n % ndev else out

    return run
