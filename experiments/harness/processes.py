"""The flags that run a CLI as one of several processes (JAX's multi-controller runtime,
``diffplan.distributed``), and what a process other than 0 does differently: nothing on stdout,
no progress bar, no file (``cli.write_json`` and the CLIs' other writers ask
:func:`writes`).

    python -m experiments.compile_p_mo2g ... --coordinator 10.0.0.1:7777 --num-processes 2 \\
        --process-id 0          # and --process-id 1 on the other host

Without the flags, JAX's own detection of a cluster of several processes (a SLURM job step of
several tasks, Open MPI, a Cloud TPU pod slice) starts the run; without either the program is
one process, exactly as without this module.
"""
from __future__ import annotations

import argparse
import os
import sys

__all__ = ["add_process_flags", "join_from_argv", "start", "writes"]

_EARLY_ERROR: list = []


def add_process_flags(parser: argparse.ArgumentParser) -> None:
    """--coordinator, --num-processes, --process-id (jax.distributed.initialize's arguments)."""
    group = parser.add_argument_group(
        "several processes (JAX's multi-controller runtime; docs/DESIGN.md, 'Several "
        "processes')")
    group.add_argument("--coordinator", metavar="HOST:PORT", default=None,
                       help="address of process 0, which listens on PORT (every process "
                            "gives the same); default: JAX's cluster detection (SLURM, Open "
                            "MPI, TPU pods), else one process")
    group.add_argument("--num-processes", type=int, default=None, metavar="N",
                       help="the number of processes of the run")
    group.add_argument("--process-id", type=int, default=None, metavar="I",
                       help="this process's index, 0..N-1 (process 0 writes every output)")


def join_from_argv(argv=None) -> None:
    """What an entry point calls first, before it imports the modules that touch JAX (some
    build arrays when imported, and ``jax.distributed.initialize`` must come before that):
    joins the run that the command line's --coordinator / --num-processes / --process-id, or
    the cluster, describes. The program's own parser (:func:`start`) checks the flags and
    reports a refusal in one line."""
    parser = argparse.ArgumentParser(add_help=False)
    add_process_flags(parser)
    known, _ = parser.parse_known_args(sys.argv[1:] if argv is None else argv)
    from diffplan import distributed

    try:
        distributed.initialize(known.coordinator, known.num_processes, known.process_id)
    except (ValueError, RuntimeError) as e:
        _EARLY_ERROR.append(e)


def start(parser: argparse.ArgumentParser, args: argparse.Namespace) -> bool:
    """Joins the run the flags (or the cluster) describe, before any JAX computation; returns
    True for a multi-process run. A process other than 0 then prints nothing on stdout and
    shows no progress bar (``args.no_progress``). Bad flags end in one line (exit 2)."""
    from diffplan import distributed

    n, i = args.num_processes, args.process_id
    if n is not None and n < 1:
        parser.error(f"--num-processes must be >= 1, got {n}")
    if i is not None and (i < 0 or (n is not None and i >= n)):
        parser.error(f"--process-id must be in 0..{'N-1' if n is None else n - 1}, got {i}")
    try:
        if _EARLY_ERROR:
            raise _EARLY_ERROR[0]
        joined = distributed.initialize(args.coordinator, n, i)
    except (ValueError, RuntimeError) as e:
        parser.error(str(e).splitlines()[0])
    if joined and not distributed.is_writer():
        if hasattr(args, "no_progress"):
            args.no_progress = True
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - for the rest of the process
    return joined


def writes() -> bool:
    """True where outputs are written: one process, or process 0 of several."""
    from diffplan import distributed

    return distributed.is_writer()
