"""Static configuration of the grid world (hashable: usable as a jit static argument)."""
from __future__ import annotations

import dataclasses

from diffplan import language
from envs.gridworld import grammar

SETTINGS = ("1o1g", "mo1g", "p_mo2g", "p_mo2g_far")
REFERENCE_SETTINGS = ("p_mo2g", "p_mo2g_far")
"""The settings whose instruction names a reference to visit first and a compass direction from
it to the target (the same sentences, grammar.TEMPLATES)."""


@dataclasses.dataclass(frozen=True)
class GridConfig:
    """One grid-world setting.

    Attributes:
      setting: "1o1g" (one object, the goal, no obstacles), "mo1g" (several distinct objects, one
        the goal), "p_mo2g" (partially observable: a visible reference object and a target that
        is not visible at t=0, in the instructed compass direction from the reference),
        "p_mo2g_far" (as p_mo2g, but the target lies beyond the view of the reference: standing
        on it does not reveal the target, the agent has to search the instructed sector).
      size: the grid is size x size cells.
      min_objects, max_objects: number of distinct objects per episode (uniform in the range).
      max_obstacles: number of obstacles is uniform in 0..max_obstacles.
      view_radius: Chebyshev radius of the field of view (a square around the agent, clipped at
        the border, accumulated over time); None means the world is fully observable.
      ref_target_radius: in p_mo2g the target lies within this Chebyshev distance of the
        reference, so that standing on the reference reveals it (must be <= view_radius); in
        p_mo2g_far the target lies at Chebyshev distance view_radius + 1 .. ref_target_radius
        from the reference, never visible from it (must be > view_radius).
      all_objects_reachable: re-draw obstacle layouts that wall off any object (distractors
        included) from the agent; otherwise only the expert path (through the reference to the
        target) must exist. True in p_mo2g_far; the paper's settings keep their episodes.
      max_steps: episode length in moves.
      language: how instructions are phrased (grammar.LANGUAGES): "canonical" (template 0),
        "paraphrased" (a training paraphrase), "unseen" (a held-out phrasing training never
        sees), "natural" (a sentence of the sealed natural-language set, envs.gridworld.natural:
        only a denoiser on pretrained features reads it; the episode's tokens are the canonical
        phrasing's), or "mixed" (training examples: canonical half of the time, else a
        training paraphrase); grammar.SPLITS.
      paraphrase: the older spelling of language="paraphrased" (True sets it).
      num_classes: number of object classes used (<= len(grammar.OBJECT_NAMES)).
    """

    setting: str = "p_mo2g"
    size: int = 16
    min_objects: int = 5
    max_objects: int = 8
    max_obstacles: int = 10
    view_radius: int | None = 6
    ref_target_radius: int = 6
    all_objects_reachable: bool = False
    max_steps: int = 100
    language: str = "canonical"
    paraphrase: bool = False
    num_classes: int = len(grammar.OBJECT_NAMES)

    def __post_init__(self):
        errors = []
        if self.paraphrase:
            if self.language not in ("canonical", "paraphrased"):
                errors.append(f"paraphrase=True contradicts language={self.language!r}")
            object.__setattr__(self, "language", "paraphrased")
            object.__setattr__(self, "paraphrase", False)
        try:
            language.check_language(self.language, languages=grammar.EVALUATION_LANGUAGES)
        except ValueError as e:
            errors.append(str(e))
        if self.setting not in SETTINGS:
            errors.append(f"unknown setting {self.setting!r}; expected one of {SETTINGS}")
        if self.size < 4:
            errors.append(f"size must be >= 4, got {self.size}")
        if not 1 <= self.num_classes <= len(grammar.OBJECT_NAMES):
            errors.append(
                f"num_classes must be in 1..{len(grammar.OBJECT_NAMES)}, got {self.num_classes}")
        if self.min_objects < 1 or self.max_objects < self.min_objects:
            errors.append(
                f"need 1 <= min_objects <= max_objects, got {self.min_objects}, {self.max_objects}")
        if self.max_objects > self.num_classes:
            errors.append(
                f"max_objects={self.max_objects} exceeds the {self.num_classes} distinct classes")
        if self.max_obstacles < 0:
            errors.append(f"max_obstacles must be >= 0, got {self.max_obstacles}")
        if self.max_objects + self.max_obstacles + 1 > self.size * self.size:
            errors.append(
                f"{self.max_objects} objects + {self.max_obstacles} obstacles + the agent do not "
                f"fit in {self.size * self.size} cells")
        if self.view_radius is not None and self.view_radius < 0:
            errors.append(f"view_radius must be >= 0 or None, got {self.view_radius}")
        if self.max_steps < self.longest_expert_path():
            errors.append(
                f"max_steps={self.max_steps} is below {self.longest_expert_path()}, the longest "
                "obstacle-free expert path of this setting: some episodes would be unsolvable")
        if self.ref_target_radius < 1:
            errors.append(f"ref_target_radius must be >= 1, got {self.ref_target_radius}")
        if self.has_reference:
            errors += self._reference_errors()
        if self.setting == "1o1g" and (self.min_objects, self.max_objects) != (1, 1):
            errors.append("1o1g has exactly one object (min_objects = max_objects = 1)")
        if errors:
            raise ValueError("invalid GridConfig: " + "; ".join(errors))

    def _reference_errors(self) -> list[str]:
        """What is wrong with the placement of the reference and the target (settings with a
        reference); [] if nothing."""
        errors, vr, rtr = [], self.view_radius, self.ref_target_radius
        if self.min_objects < 2:
            errors.append(f"{self.setting} needs min_objects >= 2 (a reference and a target)")
        if vr is None:
            return errors + [f"{self.setting} needs a finite view_radius (it is partially "
                             "observable)"]
        if self.target_beyond_reference_view:
            if vr < 1:
                errors.append(f"{self.setting} needs view_radius >= 1 (the reference is seen at "
                              f"t=0 from the agent's cell), got {vr}")
            # A reference anywhere in view has a target cell beyond both views: k cells from it
            # along its longer axis (k = min(rtr, size // 2)) is > vr from the reference and
            # >= k - vr > vr from the agent.
            if not min(rtr, self.size // 2) > 2 * vr:
                errors.append(
                    f"{self.setting} needs min(ref_target_radius, size // 2) > 2 * view_radius "
                    f"(so that every reference in view has a target cell seen neither from it "
                    f"nor from the agent), got ref_target_radius={rtr}, size={self.size}, "
                    f"view_radius={vr}")
        elif not 1 <= rtr <= vr:
            errors.append(f"ref_target_radius must be in 1..view_radius={vr}, got {rtr}")
        elif 2 * vr + 1 >= self.size:
            errors.append(
                f"view_radius={vr} sees the whole {self.size}x{self.size} grid from its centre: "
                "no target could start unseen")
        return errors

    def longest_expert_path(self) -> int:
        """Moves of the longest expert path on an obstacle-free grid of this setting."""
        if self.has_reference and self.view_radius is not None:
            return 2 * self.view_radius + 2 * self.ref_target_radius
        return 2 * (self.size - 1)

    @property
    def has_reference(self) -> bool:
        return self.setting in REFERENCE_SETTINGS

    @property
    def target_beyond_reference_view(self) -> bool:
        """The target lies view_radius + 1 .. ref_target_radius from the reference (p_mo2g_far)
        rather than within ref_target_radius <= view_radius of it (p_mo2g)."""
        return self.setting == "p_mo2g_far"

    @property
    def num_templates(self) -> int:
        return len(grammar.TEMPLATES[self.setting])

    @property
    def template_pool(self):
        """int32 (P,) the template indices this config's episodes draw their phrasing from."""
        return grammar.template_pool(self.setting, self.language)


def make_config(setting: str, **overrides) -> GridConfig:
    """The paper's configuration of a setting (Sec. 4.1), with optional overrides."""
    defaults = {
        "1o1g": dict(min_objects=1, max_objects=1, max_obstacles=0, view_radius=None),
        "mo1g": dict(min_objects=2, max_objects=8, max_obstacles=10, view_radius=None),
        "p_mo2g": dict(min_objects=5, max_objects=8, max_obstacles=10, view_radius=6),
        # Not a setting of the paper: the target 4-9 cells from the reference, unseen from it.
        "p_mo2g_far": dict(min_objects=5, max_objects=8, max_obstacles=20, view_radius=3,
                           ref_target_radius=9, all_objects_reachable=True),
    }
    if setting not in defaults:
        raise ValueError(f"unknown setting {setting!r}; expected one of {SETTINGS}")
    return GridConfig(setting=setting, **{**defaults[setting], **overrides})
