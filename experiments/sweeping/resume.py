"""What a sweep has finished, kept on disk so that a sweep that dies (a killed process, a lost
host, a full disk) resumes from the configurations it finished instead of from zero.

Each finished configuration's row is written at once to ``<first output>.parts/config_NNN.json``
(the first of ``--json``, ``--csv`` given; none: nothing is kept), with the configuration it
belongs to, by a write that is atomic (a temporary file renamed): a file there is a whole row. A
rerun of the same command takes every row whose configuration is unchanged (and whose
``--trajectories`` file is there, when asked for) and runs the rest; once its outputs are
written the directory is removed. In a multi-process run process 0 reads and writes the rows;
the others learn from it which configurations are finished (``diffplan.distributed``).
"""
from __future__ import annotations

import json
import os
import shutil

import numpy as np

__all__ = ["directory", "finished", "save", "clear"]

SUFFIX = ".parts"


def directory(args) -> str | None:
    """Where a sweep with these outputs keeps its finished rows (None: no file output)."""
    first = args.json or args.csv
    return None if first is None else first + SUFFIX


def _path(parts: str, index: int) -> str:
    return os.path.join(parts, f"config_{index:03d}.json")


def _same(a, b) -> bool:
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def _read(parts: str | None, configs: list[dict], trajectories: str | None) -> dict:
    rows = {}
    for index, config in enumerate(configs):
        try:
            with open(_path(parts, index)) as f:
                stored = json.load(f)
        except (OSError, json.JSONDecodeError):
            continue
        if not _same(stored.get("config"), config):
            continue  # another sweep's row at this index: run it again
        if trajectories and not os.path.exists(
                os.path.join(trajectories, f"config_{index:03d}.npz")):
            continue
        rows[index] = stored["row"]
    return rows


def finished(parts: str | None, configs: list[dict], trajectories: str | None) -> dict:
    """{index: row} of the configurations finished by an earlier run of this sweep (the same
    on every process; a process other than 0 gets None for the rows, which it does not
    write)."""
    from diffplan import distributed

    rows = {}
    if parts is not None and distributed.is_writer() and os.path.isdir(parts):
        rows = _read(parts, configs, trajectories)
    mask = np.zeros(len(configs), bool)
    mask[list(rows)] = True
    mask = distributed.from_writer(mask)
    return {int(i): rows.get(int(i)) for i in np.flatnonzero(mask)}


def save(parts: str | None, index: int, config: dict, row: dict) -> None:
    """Keeps a finished configuration's row (process 0; atomically)."""
    from experiments.harness.cli import atomic_file
    from experiments.harness.processes import writes

    if parts is None or not writes():
        return

    def write(tmp):
        with open(tmp, "w") as f:
            json.dump({"config": config, "row": row}, f)

    atomic_file(_path(parts, index), write)


def clear(parts: str | None) -> None:
    """Removes the kept rows once the sweep's outputs are written (process 0)."""
    from experiments.harness.processes import writes

    if parts is not None and writes() and os.path.isdir(parts):
        shutil.rmtree(parts, ignore_errors=True)
