"""Pictures of the Kuka world: top-down maps (matplotlib) and offscreen videos (mujoco.Renderer).

Maps: :func:`draw_view` draws the planner's 24 x 24 view (the top block of each cell in its
colour, a stack's height written on it once), optionally a path map, a goal cell and a pick cell,
the arm's base a "+"; row 0 (north, +y) at the top. :func:`episode_figure` puts views side by
side under the instruction, with one legend of what they show. Figures use ``matplotlib.figure.Figure`` directly (Agg), so no display is needed
and the global backend is untouched.

Videos: :func:`write_videos` renders recorded qpos frames (env.State.frames) into animated GIFs.
MuJoCo picks its GL backend when it is first imported, so rendering runs in a subprocess
(``python -m envs.kuka.render FRAMES.npz OUT_DIR``) tried with MUJOCO_GL=egl, then osmesa; where
neither works it returns None and the caller prints one line.
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile

import numpy as np

from envs.kuka import scene

_EMPTY_RGB = (0.96, 0.96, 0.96)
_PATH_RGB = (0.12, 0.12, 0.12)
_GOAL_COLOR = "#d62728"
_PICK_COLOR = "#111111"
GL_BACKENDS = ("egl", "osmesa")
FRAME_SIZE = (320, 240)


def view_image(top) -> np.ndarray:
    """float (24, 24, 3) RGB of the view's top blocks (top int (24, 24), -1 none)."""
    top = np.asarray(top)
    colors = np.array([c[:3] for c in scene.BLOCK_RGBA] + [_EMPTY_RGB], np.float32)
    return colors[np.where(top < 0, len(scene.BLOCK_RGBA), top)]


def _stack_labels(top, height):
    """[(row, col, height)]: one digit per stack taller than one block, at the cell of its top
    block nearest that block's centre (a digit in each of its 3 x 3 cells would not fit)."""
    out = []
    for block in np.unique(top[top >= 0]):
        rows, cols = np.nonzero(top == block)
        tall = height[rows, cols]
        if tall.max() <= 1:
            continue
        k = int(np.argmin((rows - rows.mean()) ** 2 + (cols - cols.mean()) ** 2))
        out.append((int(rows[k]), int(cols[k]), int(tall.max())))
    return out


def draw_view(ax, top, height, path=None, goal=None, title: str | None = None, pick=None):
    """Draws a top-down view on a matplotlib Axes: cells coloured by their top block, the height
    of each stack of two or more blocks written on it, the path's cells (bool (24, 24)) shaded
    dark, the place cell (goal, int (2,)) framed red, the pick cell (int (2,)) framed black, the
    arm's base a "+" (:func:`legend_handles` explains them)."""
    from matplotlib.patheffects import withStroke

    top, height = np.asarray(top), np.asarray(height)
    size = top.shape[0]
    ax.imshow(view_image(top), interpolation="nearest", extent=(-0.5, size - 0.5, size - 0.5, -0.5))
    for r, c, h in _stack_labels(top, height):
        ax.text(c, r, str(h), ha="center", va="center", fontsize=8, fontweight="bold",
                zorder=5, path_effects=[withStroke(linewidth=2, foreground="white")])
    if path is not None:
        overlay = np.zeros(top.shape + (4,), np.float32)
        overlay[..., :3] = _PATH_RGB
        overlay[..., 3] = 0.45 * np.asarray(path, np.float32)
        ax.imshow(overlay, interpolation="nearest",
                  extent=(-0.5, size - 0.5, size - 0.5, -0.5))
    if goal is not None:
        r, c = (int(v) for v in np.asarray(goal))
        ax.add_patch(_rect(r, c))
    if pick is not None:
        r, c = (int(v) for v in np.asarray(pick))
        ax.add_patch(_rect(r, c, _PICK_COLOR))
    ax.plot([size / 2 - 0.5], [size / 2 - 0.5], marker="+", color="k", markersize=8)
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title, fontsize=9)


def legend_handles(panels) -> list:
    """Legend entries of what :func:`draw_view` draws in these panels: the blocks' colours,
    the base, and the path, pick and place frames and stack digits where a panel has them."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    def rect(color, label):
        return Patch(facecolor="none", edgecolor=color, linewidth=1.5, label=label)

    handles = [Patch(facecolor=rgba[:3], label=f"{name} block")
               for name, rgba in zip(scene.BLOCK_NAMES, scene.BLOCK_RGBA)]
    handles.append(Line2D([], [], marker="+", color="k", markersize=8, linestyle="none",
                          label="the arm's base"))
    if any(p.get("path") is not None for p in panels):
        handles.append(Patch(facecolor=_PATH_RGB + (0.45,), label="planned carry path"))
    if any(p.get("pick") is not None for p in panels):
        handles.append(rect(_PICK_COLOR, "pick cell"))
    if any(p.get("goal") is not None for p in panels):
        handles.append(rect(_GOAL_COLOR, "place cell (goal estimate)"))
    if any(_stack_labels(np.asarray(p["top"]), np.asarray(p["height"])) for p in panels):
        handles.append(Line2D([], [], marker="$2$", color="k", markersize=7, linestyle="none",
                              label="blocks in the stack"))
    return handles


def _rect(r, c, color=_GOAL_COLOR):
    from matplotlib.patches import Rectangle

    return Rectangle((c - 0.5, r - 0.5), 1, 1, fill=False, edgecolor=color, linewidth=1.5)


def episode_figure(path: str, panels, suptitle: str = "", dpi: int = 120,
                   panel_inches: float = 2.9) -> str:
    """Writes a PNG of several views side by side, the instruction (suptitle) once above them
    and one legend below them (:func:`legend_handles`), inside the figure. panels: dicts with
    draw_view's keyword arguments (top, height, path, goal, pick, title). Returns the path."""
    import textwrap

    from matplotlib.figure import Figure

    width = max(panel_inches * len(panels) + 0.3, 5.0)
    fig = Figure(figsize=(width, panel_inches), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, panel in zip(axes, panels):
        draw_view(ax, **panel)
    handles = legend_handles(panels)
    font = 8.0
    longest = max(len(h.get_label()) for h in handles)
    ncol = max(1, min(len(handles), int(width * 72 / ((longest * 0.55 + 3.2) * font))))
    fig.legend(handles=handles, loc="outside lower center", ncol=ncol, fontsize=font,
               frameon=False, handlelength=1.4, columnspacing=1.2)
    lines = textwrap.wrap(suptitle, int(width * 72 / (9 * 0.55))) if suptitle else []
    if lines:
        fig.suptitle("\n".join(lines), fontsize=9)
    rows = -(-len(handles) // ncol)
    fig.set_size_inches(width, panel_inches + 0.35 + 0.19 * len(lines) + 0.2 * rows + 0.15)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path


# --------------------------------------------------------------------------- videos

def _render_frames(qpos_frames, camera: str = "side") -> list:
    """RGB uint8 images of qpos float (F, nq) with mujoco.Renderer (GL backend already chosen)."""
    import mujoco

    model = scene.mj_model()
    data = mujoco.MjData(model)
    renderer = mujoco.Renderer(model, FRAME_SIZE[1], FRAME_SIZE[0])
    images = []
    try:
        for qpos in np.asarray(qpos_frames):
            data.qpos[:] = qpos
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera=camera)
            images.append(renderer.render().copy())
    finally:
        renderer.close()
    return images


def _save_gif(images, path: str, fps: int = 25) -> None:
    from PIL import Image

    frames = [Image.fromarray(im) for im in images]
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=int(1000 / fps),
                   loop=0)


def write_videos(out_dir: str, videos: dict, timeout: float = 600.0):
    """Renders videos {name: qpos frames float (F, nq)} to out_dir/name.gif in a subprocess
    (MUJOCO_GL=egl, then osmesa). Returns (written paths, backend) or None when no GL backend
    works."""
    os.makedirs(out_dir, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        frames_path = os.path.join(tmp, "frames.npz")
        np.savez(frames_path, **{k: np.asarray(v, np.float32) for k, v in videos.items()})
        root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        for backend in GL_BACKENDS:
            env = dict(os.environ, MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
            env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
            try:
                proc = subprocess.run(
                    [sys.executable, "-m", "envs.kuka.render", frames_path, out_dir],
                    env=env, capture_output=True, text=True, timeout=timeout)
            except subprocess.TimeoutExpired:
                continue
            if proc.returncode == 0:
                return [os.path.join(out_dir, f"{k}.gif") for k in videos], backend
    return None


def _main(argv) -> int:
    frames_path, out_dir = argv
    with np.load(frames_path) as videos:
        for name in videos.files:
            _save_gif(_render_frames(videos[name]), os.path.join(out_dir, f"{name}.gif"))
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
