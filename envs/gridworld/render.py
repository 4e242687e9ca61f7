"""Matplotlib figures of grid-world episodes, plans and executed trajectories (Agg, no pyplot).

``render_episode`` draws one episode on an Axes or straight into a PNG file: the cells (obstacles
dark, objects labelled with a short name), the agent (blue disc), the target (red frame) and the
reference (green dashed frame), the cells not seen yet shaded grey (field of view), and optional
overlays: a path map (blue), a goal-estimate map (magenta heat map, a ring at its maximum) and an
executed trajectory (orange line). Row 0 (north) is at the top. ``episode_figure`` writes several
panels of one episode side by side with the instruction once and one legend (what is drawn, and
the object names) below them, inside the figure.

Figures are built with ``matplotlib.figure.Figure`` directly (the Agg canvas), so importing this
module never changes the global matplotlib backend and works without a display.
"""
from __future__ import annotations

import os
import pathlib
import textwrap

import numpy as np

from envs.gridworld import grammar

_EMPTY_RGB = (1.0, 1.0, 1.0)
_OBSTACLE_RGB = (0.17, 0.17, 0.19)
_OBJECT_RGB = (1.0, 0.93, 0.70)
_UNSEEN_RGBA = (0.45, 0.47, 0.52, 0.55)
_PATH_RGB = (0.12, 0.47, 0.85)
_EXPERT_RGB = (0.0, 0.62, 0.58)
_GOAL_RGB = (0.85, 0.10, 0.65)
_SUBGOAL_RGB = (0.95, 0.55, 0.0)
_AGENT_COLOR = "#1f5fbf"
_TARGET_COLOR = "#d62728"
_REFERENCE_COLOR = "#2ca02c"
_EXECUTED_COLOR = "#ff7f0e"


def short_names(names) -> list[str]:
    """The shortest prefix (at least 3 letters) of each name that no other name shares."""
    names = [str(n) for n in names]
    out = []
    for name in names:
        others = [o for o in names if o != name]
        length = min(3, len(name))
        while length < len(name) and any(o.startswith(name[:length]) for o in others):
            length += 1
        out.append(name[:length])
    return out


def _unit_map(values, name: str, shape) -> np.ndarray:
    """A bool or float (H, W) map -> float (H, W) in [0, 1]. Floats with negative entries are taken
    to be in the planner's [-1, 1] convention and mapped by (v + 1) / 2; then clipped to [0, 1]."""
    values = np.asarray(values)
    if values.shape != tuple(shape):
        raise ValueError(f"{name} must have the grid's shape {tuple(shape)}, got {values.shape}")
    if values.dtype == bool:
        return values.astype(np.float32)
    values = np.nan_to_num(values.astype(np.float32), nan=0.0)
    if values.min() < 0:
        values = (values + 1.0) / 2.0
    return np.clip(values, 0.0, 1.0)


def _cell(pos, name: str):
    """(row, col) ints or None for a missing (-1, -1) / None cell."""
    if pos is None:
        return None
    pos = np.asarray(pos).reshape(-1)
    if pos.shape != (2,):
        raise ValueError(f"{name} must be a (row, col) pair, got shape {pos.shape}")
    if np.all(pos < 0):
        return None
    return int(pos[0]), int(pos[1])


def _draw(ax, grid, agent, target, reference, *, seen=None, path=None, goal=None,
          executed=None, subgoal=None, object_names=None, path_label: str = "path",
          title=None):
    """Draws an episode's map and overlays on ax (no legend); returns (legend handles of
    what was drawn, in order, object classes present)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Circle, Patch, Rectangle
    from matplotlib.patheffects import withStroke

    grid = np.asarray(grid)
    if grid.ndim != 2:
        raise ValueError(f"grid must be (H, W), got shape {grid.shape}")
    h, w = grid.shape
    names = list(object_names) if object_names is not None else list(grammar.OBJECT_NAMES)
    labels = short_names(names)
    cell_size = min(1.0, 16.0 / max(h, w))
    font = 6.0 * cell_size + 1.0

    image = np.empty((h, w, 3), np.float32)
    image[:] = _EMPTY_RGB
    image[grid < 0] = _OBSTACLE_RGB
    image[grid > 0] = _OBJECT_RGB
    extent = (-0.5, w - 0.5, h - 0.5, -0.5)
    ax.imshow(image, extent=extent, interpolation="nearest", zorder=0)
    handles = []
    if (grid < 0).any():
        handles.append(Patch(facecolor=_OBSTACLE_RGB, label="obstacle"))

    if path is not None:
        color = _EXPERT_RGB if path_label == "expert path" else _PATH_RGB
        p = _unit_map(path, "path", grid.shape)
        layer = np.zeros((h, w, 4), np.float32)
        layer[..., :3] = color
        layer[..., 3] = 0.5 * p
        ax.imshow(layer, extent=extent, interpolation="nearest", zorder=1)
        handles.append(Patch(facecolor=color + (0.5,), label=path_label))
    if goal is not None:
        g = _unit_map(goal, "goal", grid.shape)
        if g.max() > 0:
            g_norm = g / g.max()
            layer = np.zeros((h, w, 4), np.float32)
            layer[..., :3] = _GOAL_RGB
            layer[..., 3] = 0.55 * g_norm
            ax.imshow(layer, extent=extent, interpolation="nearest", zorder=1)
            best = np.unravel_index(np.argmax(g), g.shape)
            # A ring (not a filled marker) so that the cell's object label stays readable.
            ax.plot(best[1], best[0], marker="o", markersize=14 * cell_size, fillstyle="none",
                    color=_GOAL_RGB, markeredgewidth=2.0, linestyle="none", zorder=6)
        handles.append(Line2D([], [], marker="o", fillstyle="none", color=_GOAL_RGB,
                              markeredgewidth=2, linestyle="none", label="goal estimate"))
    if subgoal is not None:
        sg = _unit_map(subgoal, "subgoal", grid.shape)
        best = np.unravel_index(np.argmax(sg), sg.shape)
        ax.plot(best[1], best[0], marker="D", markersize=11 * cell_size, fillstyle="none",
                color=_SUBGOAL_RGB, markeredgewidth=1.8, linestyle="none", zorder=6)
        handles.append(Line2D([], [], marker="D", fillstyle="none", color=_SUBGOAL_RGB,
                              markeredgewidth=2, linestyle="none", label="sub-goal"))
    if seen is not None:
        s = np.asarray(seen)
        if s.shape != grid.shape:
            raise ValueError(f"seen must have the grid's shape {grid.shape}, got {s.shape}")
        layer = np.zeros((h, w, 4), np.float32)
        layer[~s.astype(bool)] = _UNSEEN_RGBA
        ax.imshow(layer, extent=extent, interpolation="nearest", zorder=2)
        handles.append(Patch(facecolor=_UNSEEN_RGBA, label="not seen yet"))

    present = sorted({int(k) for k in np.unique(grid) if k > 0})
    for r, c in zip(*np.nonzero(grid > 0)):
        k = int(grid[r, c])
        label = labels[k - 1] if 0 < k <= len(labels) else str(k)
        # Above every marker, outlined in white, so that the agent, rings and frames on an
        # object's cell never hide its name.
        ax.text(c, r, label, ha="center", va="center", fontsize=font, zorder=10,
                color="black", path_effects=[withStroke(linewidth=2.2, foreground="white")])

    target_cell = _cell(target, "target")
    reference_cell = _cell(reference, "reference")
    agent_cell = _cell(agent, "agent")
    if target_cell is not None:
        ax.add_patch(Rectangle((target_cell[1] - 0.46, target_cell[0] - 0.46), 0.92, 0.92,
                               fill=False, edgecolor=_TARGET_COLOR, linewidth=2.2, zorder=4))
        handles.append(Patch(facecolor="none", edgecolor=_TARGET_COLOR, linewidth=2,
                             label="target"))
    if reference_cell is not None:
        ax.add_patch(Rectangle((reference_cell[1] - 0.46, reference_cell[0] - 0.46), 0.92, 0.92,
                               fill=False, edgecolor=_REFERENCE_COLOR, linewidth=2.2,
                               linestyle=(0, (2, 1)), zorder=4))
        handles.append(Patch(facecolor="none", edgecolor=_REFERENCE_COLOR, linewidth=2,
                             linestyle="--", label="reference"))
    if executed is not None:
        e = np.asarray(executed)
        if e.ndim != 2 or e.shape[1] != 2:
            raise ValueError(f"executed must be (T, 2) positions, got shape {e.shape}")
        if len(e):
            ax.plot(e[:, 1], e[:, 0], color=_EXECUTED_COLOR, linewidth=2.0, alpha=0.9,
                    marker="o", markersize=2.5, zorder=6, solid_capstyle="round")
        handles.append(Line2D([], [], color=_EXECUTED_COLOR, marker="o", markersize=3,
                              label="executed"))
    if agent_cell is not None:
        ax.add_patch(Circle((agent_cell[1], agent_cell[0]), 0.3, facecolor=_AGENT_COLOR,
                            edgecolor="white", linewidth=1.0, zorder=8, alpha=0.85))
        handles.insert(0, Line2D([], [], marker="o", color=_AGENT_COLOR, linestyle="none",
                                 label="agent"))

    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_xticks(np.arange(-0.5, w, 1.0), minor=True)
    ax.set_yticks(np.arange(-0.5, h, 1.0), minor=True)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.grid(which="minor", color="#c8c8c8", linewidth=0.5)
    ax.tick_params(which="both", length=0)
    ax.set_aspect("equal")
    if title is not None:
        ax.set_title(str(title), fontsize=9)
    return handles, present


def object_key(present, object_names=None) -> list[str]:
    """"app = apple"-style entries of the object classes present (grid values k >= 1)."""
    names = list(object_names) if object_names is not None else list(grammar.OBJECT_NAMES)
    labels = short_names(names)
    return [f"{labels[k - 1]} = {names[k - 1]}" for k in present if k <= len(names)]


def episode_figure(path, panels, instruction: str = "", object_names=None, dpi: int = 120,
                   panel_inches: float = 3.4):
    """Writes a PNG of one episode's panels side by side: the instruction once, above them,
    and one legend below them, inside the figure, of everything the panels draw and of the
    object names (the labels in the cells).

    panels: dicts of :func:`render_episode`'s arguments (grid, agent, target, reference,
    seen, path, goal, subgoal, executed, title; path_label "path" or "expert path", drawn
    in another colour). Returns the pathlib.Path written."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    out = pathlib.Path(path)
    n = len(panels)
    width = max(panel_inches * n + 0.3, 4.6)
    fig = Figure(figsize=(width, panel_inches), layout="constrained")
    axes = fig.subplots(1, n, squeeze=False)[0]
    handles, present = {}, set()
    for ax, panel in zip(axes, panels):
        drawn, objects = _draw(ax, **panel, object_names=object_names)
        for handle in drawn:
            handles.setdefault(handle.get_label(), handle)
        present.update(objects)
    entries = list(handles.values()) + [
        Patch(facecolor=_OBJECT_RGB, edgecolor="#c8c8c8", label=key)
        for key in object_key(sorted(present), object_names)]
    font = 8.0
    longest = max([len(h.get_label()) for h in entries] + [1])
    ncol = max(1, min(len(entries), int(width * 72 / ((longest * 0.55 + 3.2) * font))))
    fig.legend(handles=entries, loc="outside lower center", ncol=ncol, fontsize=font,
               frameon=False, handlelength=1.4, columnspacing=1.2)
    lines = []
    if instruction:
        lines = textwrap.wrap(f"\u201c{instruction}\u201d", int(width * 72 / (10 * 0.55)))
        fig.suptitle("\n".join(lines), fontsize=10)
    # Room for the panel titles, the instruction's lines and the legend's rows.
    rows = -(-len(entries) // ncol)
    fig.set_size_inches(width, panel_inches + 0.35 + 0.2 * len(lines) + 0.2 * rows + 0.15)
    fig.savefig(out, dpi=dpi, format="png")
    return out


def render_episode(ax_or_path, grid, agent, target, reference, instruction, *, seen=None,
                   path=None, goal=None, subgoal=None, executed=None, title=None,
                   object_names=None, dpi=130, path_label: str = "path"):
    """Draws one episode.

    Args:
      ax_or_path: a matplotlib Axes to draw on (its title says the instruction, a legend and
        the object names go under it), or a file path: a PNG is written there with
        :func:`episode_figure` (one panel).
      grid: int (H, W) 0 empty, -1 obstacle, k >= 1 object class k (object_names[k - 1]).
      agent, target, reference: (row, col); reference (-1, -1) or None when there is none.
      instruction: str, shown under the title ("" or None for none).
      seen: bool (H, W) cells seen so far; the others are shaded grey.
      path: bool or float (H, W) path map (floats in [-1, 1] or [0, 1]), overlaid in blue
        (path_label "expert path": in teal), its legend entry path_label.
      goal: float (H, W) goal-estimate map (same ranges), a magenta heat map with a ring at its
        maximum.
      subgoal: float (H, W) sub-goal map (same ranges), a diamond at its maximum.
      executed: int (T, 2) positions the agent went through, drawn as a line.
      title: optional title line; object_names: class names (default grammar.OBJECT_NAMES).
    Returns:
      the Axes, or the pathlib.Path of the PNG written.
    """
    panel = dict(grid=grid, agent=agent, target=target, reference=reference, seen=seen,
                 path=path, goal=goal, subgoal=subgoal, executed=executed, path_label=path_label)
    if hasattr(ax_or_path, "imshow"):
        ax = ax_or_path
        handles, present = _draw(ax, **panel, object_names=object_names)
        heading = [] if title is None else [str(title)]
        if instruction:
            heading += textwrap.wrap(f"\u201c{instruction}\u201d", width=62)
        if heading:
            ax.set_title("\n".join(heading), fontsize=8.5)
        if handles:
            ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.01),
                      ncol=min(4, len(handles)), fontsize=7, frameon=False, handlelength=1.4)
        if key := ", ".join(object_key(present, object_names)):
            ax.text(0.5, -0.13, "\n".join(textwrap.wrap(key, width=80)),
                    transform=ax.transAxes, ha="center", va="top", fontsize=6.5,
                    color="#333333")
        return ax
    if not isinstance(ax_or_path, (str, os.PathLike)):
        raise ValueError(f"ax_or_path must be a matplotlib Axes or a file path, got "
                         f"{type(ax_or_path).__name__}")
    return episode_figure(ax_or_path, [dict(panel, title=title)], instruction or "",
                          object_names=object_names, dpi=dpi, panel_inches=4.2)


def save_export_figures(arrays: dict, out_dir, num: int, *, prefix: str = "episode") -> list:
    """PNG figures of the first ``num`` episodes of an export dict (envs.gridworld.export), with
    the expert path and the cells visible at t=0; files ``{prefix}_{i:05d}.png`` in out_dir.
    Returns the paths written."""
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = [str(n) for n in arrays["object_names"]]
    paths = []
    for i in range(min(int(num), len(arrays["grid"]))):
        title = (f"{prefix} episode {i}: expert path {int(arrays['expert_length'][i])} moves")
        paths.append(render_episode(
            out_dir / f"{prefix}_{i:05d}.png", arrays["grid"][i], arrays["agent"][i],
            arrays["target"][i], arrays["reference"][i], str(arrays["instruction"][i]),
            seen=arrays["visible0"][i], path=arrays["expert_path"][i], title=title,
            object_names=names, path_label="expert path"))
    return paths
