"""Pictures of the Kuka world: top-down maps (matplotlib) and offscreen videos (mujoco.Renderer).

Maps: :func:`draw_view` draws the planner's 24 x 24 view (the top block of each cell in its
colour, the stack height written in it), optionally a path map, a goal cell and a pick cell;
row 0 (north, +y) at the top. Figures use ``matplotlib.figure.Figure`` directly (Agg), so no display is needed
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


def draw_view(ax, top, height, path=None, goal=None, title: str | None = None, pick=None):
    """Draws a top-down view on a matplotlib Axes: cells coloured by their top block, stack
    heights > 1 written in, the path's cells (bool (24, 24)) shaded dark, the goal cell
    (int (2,)) framed red, the pick cell (int (2,)) framed black."""
    top, height = np.asarray(top), np.asarray(height)
    size = top.shape[0]
    ax.imshow(view_image(top), interpolation="nearest", extent=(-0.5, size - 0.5, size - 0.5, -0.5))
    for r, c in zip(*np.nonzero(height > 1)):
        ax.text(c, r, str(int(height[r, c])), ha="center", va="center", fontsize=6)
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
        ax.set_title(title, fontsize=8)


def _rect(r, c, color=_GOAL_COLOR):
    from matplotlib.patches import Rectangle

    return Rectangle((c - 0.5, r - 0.5), 1, 1, fill=False, edgecolor=color, linewidth=1.5)


def episode_figure(path: str, panels, suptitle: str = "") -> str:
    """Writes a PNG of several views side by side. panels: dicts with draw_view's keyword
    arguments (top, height, path, goal, title). Returns the path."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(2.6 * len(panels), 3.0))
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, panel in zip(axes, panels):
        draw_view(ax, **panel)
    if suptitle:
        fig.suptitle(suptitle, fontsize=7, wrap=True)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=120)
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
