"""Overrides of ``envs.make``: split by the dataclass whose field each names."""
from __future__ import annotations

import dataclasses


def split_overrides(name: str, overrides: dict, **targets) -> dict[str, dict]:
    """{target: the overrides naming a field of its dataclass}; ``targets`` maps a label to
    (dataclass, fields it does not take from overrides). An override no target takes is a
    ValueError naming it and what each target takes."""
    fields = {label: {f.name for f in dataclasses.fields(cls)} - set(excluded)
              for label, (cls, excluded) in targets.items()}
    unknown = sorted(set(overrides) - set().union(*fields.values()))
    if unknown:
        takes = ", ".join(f"the {label} takes {sorted(names)}" for label, names in fields.items())
        raise ValueError(f"unknown override(s) {unknown} for {name}; {takes}")
    return {label: {k: v for k, v in overrides.items() if k in names}
            for label, names in fields.items()}
