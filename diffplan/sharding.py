"""Data parallelism over all JAX devices through ``jax.sharding``.

One 1-D mesh named ``"data"`` spans the devices. Batches are split along their leading axis
(``P("data")``); parameters, optimizer state and PRNG keys are replicated (``P()``). XLA's SPMD
partitioner then inserts the gradient all-reduce, so a sharded train step computes the same
numbers as a single-device one (up to float summation order). With one device every helper is
a no-op placement on that device.

On a CPU-only machine, several host "devices" for testing are obtained with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (set before JAX initialises).

Typical use::

    mesh = data_mesh()
    params = replicate(params, mesh)
    batch = shard_batch(batch, mesh)                       # leading axis split over "data"
    f = data_parallel_jit(fn, mesh, batched_argnums=(1,))  # fn(params, x) -> batched output
    y = f(params, x)
"""
from __future__ import annotations

import functools
from typing import Any, Callable, Optional, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

__all__ = [
    "DATA_AXIS",
    "data_mesh",
    "replicated_sharding",
    "batch_sharding",
    "batch_size_of",
    "check_divisible",
    "shard_batch",
    "replicate",
    "constrain_batch",
    "constrain_replicated",
    "data_parallel_jit",
    "per_device",
    "PerDevice",
]

DATA_AXIS = "data"


def data_mesh(devices: Optional[Sequence[jax.Device]] = None) -> Mesh:
    """A 1-D mesh with axis ``"data"`` over ``devices`` (default: all of ``jax.devices()``)."""
    devs = list(jax.devices() if devices is None else devices)
    if not devs:
        raise ValueError("data_mesh needs at least one device")
    return Mesh(np.asarray(devs, dtype=object), (DATA_AXIS,))


def replicated_sharding(mesh: Mesh) -> NamedSharding:
    """Every device holds the whole array."""
    return NamedSharding(mesh, P())


def batch_sharding(mesh: Mesh) -> NamedSharding:
    """The leading axis is split evenly over the ``"data"`` axis; other axes are whole."""
    return NamedSharding(mesh, P(DATA_AXIS))


def batch_size_of(tree: Any) -> int:
    """The common leading dimension of every array leaf of ``tree``.

    Raises:
      ValueError: if a leaf is a scalar, if leading dimensions differ, or there are no leaves.
    """
    leaves = jax.tree_util.tree_leaves_with_path(tree)
    if not leaves:
        raise ValueError("batch has no array leaves")
    sizes = {}
    for path, leaf in leaves:
        shape = np.shape(leaf)
        if len(shape) == 0:
            raise ValueError(f"batch leaf {jax.tree_util.keystr(path) or '<root>'} is a scalar; "
                             "every batch leaf needs a leading batch axis")
        sizes[jax.tree_util.keystr(path) or "<root>"] = shape[0]
    if len(set(sizes.values())) != 1:
        raise ValueError(f"batch leaves have different leading (batch) sizes: {sizes}")
    return next(iter(sizes.values()))


def check_divisible(batch_size: int, mesh: Mesh) -> None:
    """Raises ValueError unless ``batch_size`` splits evenly over the mesh's devices."""
    n = mesh.size
    if batch_size % n:
        raise ValueError(
            f"batch size {batch_size} is not divisible by the number of devices {n} on the "
            f"'{DATA_AXIS}' mesh axis; use a multiple of {n}")


def _place(tree: Any, sharding: NamedSharding) -> Any:
    """``jax.device_put(tree, sharding)``; on a mesh over several processes
    (``diffplan.distributed``) each leaf that is not yet a global array (numpy, or an array of
    this process's devices) holds the same value on every process, and each process places
    its own devices' parts of it (no cross-process check, no transfer)."""
    if sharding.is_fully_addressable:
        return jax.device_put(tree, sharding)

    def leaf(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return x if x.sharding == sharding else jax.device_put(x, sharding)
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree_util.tree_map(leaf, tree)


def shard_batch(tree: Any, mesh: Mesh) -> Any:
    """Places every leaf of ``tree`` with its leading axis split over ``"data"``.

    Leaves must share the leading dimension, divisible by the number of devices.
    """
    check_divisible(batch_size_of(tree), mesh)
    return _place(tree, batch_sharding(mesh))


def replicate(tree: Any, mesh: Mesh) -> Any:
    """Places a full copy of every leaf of ``tree`` on every device of ``mesh``."""
    return _place(tree, replicated_sharding(mesh))


def constrain_batch(tree: Any, mesh: Mesh) -> Any:
    """Inside ``jit``: asks XLA to keep ``tree``'s leading axis split over ``"data"``."""
    check_divisible(batch_size_of(tree), mesh)
    return jax.lax.with_sharding_constraint(tree, batch_sharding(mesh))


def constrain_replicated(tree: Any, mesh: Mesh) -> Any:
    """Inside ``jit``: asks XLA to keep every leaf of ``tree`` replicated."""
    return jax.lax.with_sharding_constraint(tree, replicated_sharding(mesh))


def data_parallel_jit(fn: Callable, mesh: Mesh, *, batched_argnums: Sequence[int] = (0,),
                      out_batched: Any = True, donate_argnums: Sequence[int] = ()) -> Callable:
    """``jit(fn)`` with batched arguments split over ``"data"`` and the others replicated.

    Args:
      fn: a pure function of positional array pytrees (close over static values).
      mesh: from ``data_mesh``.
      batched_argnums: positions of arguments whose leaves all have the leading batch axis
        (their batch size must be divisible by the number of devices).
      out_batched: True if every output leaf has the leading batch axis (split over
        ``"data"``), False if every output is replicated, or a pytree prefix of bools matching
        the output structure.
      donate_argnums: forwarded to ``jax.jit``.

    Returns:
      A callable with ``fn``'s signature. It places its arguments (``shard_batch`` /
      ``replicate``, a no-op when they are already placed) and calls the jitted function, which
      is available as ``.jitted_for(num_args)`` for callers that place inputs themselves.
    """
    batched = frozenset(int(i) for i in batched_argnums)
    in_b, in_r = batch_sharding(mesh), replicated_sharding(mesh)

    def out_spec(flag):
        return in_b if flag else in_r

    if isinstance(out_batched, bool):
        out_shardings = out_spec(out_batched)
    else:
        out_shardings = jax.tree_util.tree_map(out_spec, out_batched)

    cache = {}

    def get_jitted(nargs: int):
        if nargs not in cache:
            bad = [i for i in batched if i >= nargs or i < 0]
            if bad:
                raise ValueError(f"batched_argnums {sorted(bad)} out of range for {nargs} args")
            in_shardings = tuple(in_b if i in batched else in_r for i in range(nargs))
            cache[nargs] = jax.jit(fn, in_shardings=in_shardings, out_shardings=out_shardings,
                                   donate_argnums=tuple(donate_argnums))
        return cache[nargs]

    @functools.wraps(fn)
    def wrapper(*args):
        placed = tuple(shard_batch(a, mesh) if i in batched else replicate(a, mesh)
                       for i, a in enumerate(args))
        return get_jitted(len(args))(*placed)

    wrapper.jitted_for = get_jitted
    return wrapper


def per_device(fn: Callable, mesh: Mesh, *, num_replicated: int = 1) -> Callable:
    """``jit(shard_map(fn))``: every device runs ``fn`` on its own slice of the batch, with no
    communication; for computations whose per-row results do not depend on the other rows
    (e.g. an evaluation's episodes, each with its own key).

    ``fn(*replicated, *batched)``: the first ``num_replicated`` arguments (e.g. the planner and
    its parameters) are copied to every device; the leaves of the others and of the output
    have a leading batch axis, split over ``"data"`` (its size divisible by the number of
    devices; each device sees batch / devices rows). With one device this is ``jit(fn)``.
    """
    from jax.experimental.shard_map import shard_map

    def wrapped(*args):
        in_specs = tuple(P() if i < num_replicated else P(DATA_AXIS)
                         for i in range(len(args)))
        for a in args[num_replicated:]:
            check_divisible(batch_size_of(a), mesh)
        return shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=P(DATA_AXIS),
                         check_rep=False)(*args)

    return jax.jit(wrapped)


class PerDevice:
    """``jit(shard_map(fn))`` over a mesh, like :func:`per_device`, that places its own
    arguments: those at ``replicated_argnums`` are copied to every device, the others split
    along their leading axis (its size divisible by the mesh's devices); outputs are split.
    Arguments may be numpy or jax arrays holding the same values on every process (a mesh over
    several processes, ``diffplan.distributed``); outputs are global arrays (read them with
    ``diffplan.distributed.gather``). ``lower(*args).compile()`` gives a callable that places
    its arguments the same way (for programs compiled ahead of time)."""

    def __init__(self, fn: Callable, mesh: Mesh, *, replicated_argnums: Sequence[int] = (0,)):
        from jax.experimental.shard_map import shard_map

        self.mesh = mesh
        self.replicated = frozenset(int(i) for i in replicated_argnums)
        self._fn = fn
        self._jitted = {}
        self._shard_map = shard_map

    def _jit(self, nargs: int):
        if nargs not in self._jitted:
            specs = tuple(P() if i in self.replicated else P(DATA_AXIS) for i in range(nargs))
            self._jitted[nargs] = jax.jit(self._shard_map(
                self._fn, mesh=self.mesh, in_specs=specs, out_specs=P(DATA_AXIS),
                check_rep=False))
        return self._jitted[nargs]

    def place(self, args: Sequence[Any]) -> tuple:
        """The arguments placed on the mesh (replicated or split)."""
        return tuple(replicate(a, self.mesh) if i in self.replicated
                     else shard_batch(a, self.mesh) for i, a in enumerate(args))

    def __call__(self, *args):
        return self._jit(len(args))(*self.place(args))

    def lower(self, *args):
        jitted, place = self._jit(len(args)), self.place

        class Lowered:
            def __init__(self, lowered):
                self.lowered = lowered

            def compile(self):
                compiled = self.lowered.compile()
                return lambda *a: compiled(*place(a))

        return Lowered(jitted.lower(*place(args)))
