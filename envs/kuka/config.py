"""The Kuka tasks: the four columns of the paper's Table 2 (:class:`TaskSpec`, hashable, a static
argument under jit), and the sizes every task shares.

Following Diffuser and Decision Diffuser, a task is a set of "X on Y" relations the arm must
build, and success is the share of instructed relations that hold at the end:

* stacking, multi-constraint: one tower of all four blocks in a fully instructed order, 3
  instructed relations;
* stacking, single constraint: one tower of all four blocks, one instructed relation; the order
  of the rest is free;
* rearrangement, single constraint: one relation "X on Y", the other blocks stay where they are;
* rearrangement, multi-constraint: two relations (two towers of two, or a tower of three).

The episodes of a task are generated in :mod:`envs.kuka.episode`.
"""
from __future__ import annotations

import dataclasses

from envs.kuka import grammar

MAX_RELATIONS = grammar.MAX_RELATIONS
NO_BLOCK = -1

@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """A task (hashable; pass as a static argument). kind: "stacking" or "rearrangement";
    multi: several instructed relations (3 stacking, 2 rearrangement) or one; language: one
    of grammar.LANGUAGES ("canonical", "paraphrased", "development": phrasings training never
    sees but that were chosen on, "heldout": the sealed held-out phrasings), "natural" (the
    sealed natural-language set, envs.kuka.natural: only a denoiser on pretrained text
    features reads it), or for training only "broad" (the training paraphrases and the extra
    phrasings, grammar.EXTRA)."""

    kind: str
    multi: bool = False
    language: str = "canonical"

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"unknown task kind {self.kind!r}; expected one of {KINDS}")
        grammar.check_phrasing(self.language)

    @property
    def name(self) -> str:
        return f"{self.kind}_{'multi' if self.multi else 'single'}"

    @property
    def num_constraints(self) -> int:
        if not self.multi:
            return 1
        return 3 if self.kind == "stacking" else 2

    @property
    def max_steps(self) -> int:
        """Placements allowed: twice what the task needs (3 for a tower, else one per
        relation), so a planner can correct a mistake."""
        needed = 3 if self.kind == "stacking" else self.num_constraints
        return 2 * needed


KINDS = ("stacking", "rearrangement")
MAX_STEPS = 6
"""The largest max_steps of any task (stacking's)."""
COLUMNS = {spec.name: spec for spec in (
    TaskSpec("stacking", False), TaskSpec("rearrangement", False),
    TaskSpec("stacking", True), TaskSpec("rearrangement", True))}
"""The four columns of Table 2, by name."""
