"""One program on several processes, through JAX's own multi-controller runtime.

Every process runs the same program (``jax.distributed.initialize``; on CPU the collectives run
over gloo). ``jax.devices()`` is then the devices of all processes, so the mesh of
``diffplan.sharding.data_mesh()`` spans them and a jitted program over it runs on every
process at once, each on its own devices. With one process (nothing initialised) every helper
here is the plain single-process operation, so a program written with them runs unchanged.

- :func:`initialize`: joins the processes (the arguments of ``jax.distributed.initialize``),
  or JAX's own detection of a cluster of several processes (SLURM, Open MPI, Cloud TPU pods),
  or nothing: one process, exactly as without this module.
- :func:`gather`: a program's output (split over the devices of all processes) as numpy arrays
  on every process.
- :func:`is_writer`: process 0 writes every file (results, checkpoints, logs); the others
  compute their share and write nothing.
- :func:`from_writer`: process 0's value of a small host value (e.g. what a file it read says),
  the same on every process.

Needs: the coordinator (process 0) listens on one TCP port that every process reaches; every
process runs the same computations in the same order (the CLIs do: they draw the same episodes
from the same seeds); files that every process reads (checkpoints) are on a filesystem each of
them sees.
"""
from __future__ import annotations

import os
import warnings
from typing import Any, Optional

import jax
import numpy as np

__all__ = ["initialize", "detected_cluster", "is_initialized", "process_index",
           "process_count", "is_writer", "gather", "from_writer", "agree", "barrier",
           "environment_summary"]


def detected_cluster() -> Optional[str]:
    """The name of the cluster environment JAX detects with more than one process (SLURM,
    Open MPI, a Cloud TPU pod, ...), or None: the environments ``jax.distributed.initialize()``
    would configure itself from, restricted to those that run several processes (a one-task
    SLURM job stays a plain process)."""
    try:  # JAX's own detectors (the ones initialize() uses when its arguments are absent)
        from jax._src.clusters import ClusterEnv
    except ImportError:  # pragma: no cover - a future JAX that moved them
        return None
    for env in ClusterEnv._cluster_types:  # noqa: SLF001
        if getattr(env, "opt_in_only_method", False):
            continue
        try:
            with warnings.catch_warnings():  # e.g. a Kubernetes pod without `kubernetes`
                warnings.simplefilter("ignore")
                if env.is_env_present() and int(env.get_process_count()) > 1:
                    return env.__name__
        except Exception:  # noqa: BLE001 - a detector that cannot tell is no cluster
            continue
    return None


def is_initialized() -> bool:
    """True once :func:`initialize` (or ``jax.distributed.initialize``) joined processes."""
    return bool(jax.distributed.is_initialized())


def initialize(coordinator: Optional[str] = None, num_processes: Optional[int] = None,
               process_id: Optional[int] = None, *,
               initialization_timeout: int = 300) -> bool:
    """Joins this process to a multi-process run; returns True if it did (False: one process).

    With any argument: ``jax.distributed.initialize(coordinator_address=coordinator,
    num_processes=..., process_id=...)`` (JAX fills absent ones from the environment). Without
    arguments: ``jax.distributed.initialize()`` when :func:`detected_cluster` names a cluster of
    several processes, else nothing. Must run before any JAX computation. CPU collectives are
    set to gloo first (the CPU backend then runs cross-process programs). Calling it again
    after a successful call does nothing.

    Raises ValueError (one line) for arguments JAX refuses.
    """
    if is_initialized():
        return True
    given = (coordinator, num_processes, process_id)
    if all(v is None for v in given) and detected_cluster() is None:
        return False
    if coordinator is not None and (":" not in coordinator
                                    or not coordinator.rsplit(":", 1)[1].isdigit()):
        raise ValueError(f"the coordinator must be HOST:PORT, got {coordinator!r}")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    try:
        jax.distributed.initialize(coordinator_address=coordinator,
                                   num_processes=num_processes, process_id=process_id,
                                   initialization_timeout=initialization_timeout)
    except (ValueError, TypeError) as e:
        raise ValueError(f"cannot start the multi-process run: {e}") from e
    return True


def process_index() -> int:
    """This process's index (0 with one process)."""
    return int(jax.process_index())


def process_count() -> int:
    """The number of processes (1 unless initialised)."""
    return int(jax.process_count())


def is_writer() -> bool:
    """True on the one process that writes files and prints results: process 0."""
    return process_index() == 0


def _fully_addressable(x) -> bool:
    return not isinstance(x, jax.Array) or x.is_fully_addressable or x.is_fully_replicated


def gather(tree: Any) -> Any:
    """``tree`` as numpy arrays, whole, on every process: a leaf this process holds whole (a
    local array, numpy, or one replicated everywhere) is read as it is; the leaves split over
    the devices of several processes are all-gathered (``multihost_utils.process_allgather``,
    one call for all of them)."""
    leaves, treedef = jax.tree.flatten(tree)
    split = [i for i, x in enumerate(leaves) if not _fully_addressable(x)]
    out = [None] * len(leaves)
    if split:
        from jax.experimental import multihost_utils

        whole = multihost_utils.process_allgather([leaves[i] for i in split], tiled=True)
        for i, value in zip(split, whole):
            out[i] = np.asarray(value)
    rest = [i for i in range(len(leaves)) if out[i] is None]
    for i, value in zip(rest, jax.device_get([leaves[i] for i in rest])):
        out[i] = np.asarray(value)
    return jax.tree.unflatten(treedef, out)


def from_writer(tree: Any) -> Any:
    """Process 0's value of ``tree`` (small numpy arrays or scalars, the same structure on
    every process) on every process; the value itself with one process."""
    if process_count() == 1:
        return tree
    from jax.experimental import multihost_utils

    return jax.tree.map(np.asarray, multihost_utils.broadcast_one_to_all(tree))


def agree(value: int, what: str) -> None:
    """Raises ValueError on every process unless every process holds the same integer
    ``value`` (``what`` it is, for the message); nothing with one process."""
    if process_count() == 1:
        return
    from jax.experimental import multihost_utils

    values = np.asarray(multihost_utils.process_allgather(np.asarray([int(value)], np.int64),
                                                          tiled=True)).tolist()
    if len(set(values)) > 1:
        raise ValueError(f"the processes disagree on {what}: {values} (process i's at "
                         "position i); each must see the same files")


def barrier(name: str) -> None:
    """Every process waits here until all arrive (nothing with one process). ``name`` must be
    the same on every process and new each time."""
    if process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def environment_summary() -> str:
    """One line: process i of N, its devices, the global device count (for logs)."""
    return (f"process {process_index()} of {process_count()} (pid {os.getpid()}), "
            f"{jax.local_device_count()} local of {jax.device_count()} "
            f"{jax.devices()[0].platform} devices")
