"""Every figure kind the project writes, rendered on a tiny input, is checked with matplotlib's
own renderer: no two texts overlap (titles, labels, tick labels, legend entries, annotations),
every text and legend lies inside the canvas, no legend covers a text of its own figure that is
not in it, and every text is at least MIN_PIXELS high at the dpi the PNG is written with
(readable at 100% zoom). The figures are caught as the project's code saves them
(Figure.savefig), so what is checked is what is written. A planted overlap, a text off the
canvas and a tiny label are caught (the control)."""
from __future__ import annotations

import numpy as np
import pytest

MIN_PIXELS = 9.0
"""The smallest text height, in pixels of the written PNG (a font's size in points x dpi / 72)."""


def _drawn_tick_labels(ax):
    """The tick labels matplotlib draws: the ticks within the view (Axis._update_ticks)."""
    out = []
    for axis in (ax.xaxis, ax.yaxis):
        for tick in axis._update_ticks():
            out += [label for label in (tick.label1, tick.label2)
                    if label.get_visible() and label.get_text().strip()]
    return out


def layout_problems(fig, dpi=None) -> list[str]:
    """What is wrong with a figure's layout, one line each ([] when nothing is): overlapping
    texts, a text or legend outside the canvas, a legend over another text, a text smaller than
    MIN_PIXELS at ``dpi`` (default the figure's)."""
    from matplotlib.axis import Tick
    from matplotlib.legend import Legend
    from matplotlib.text import Text

    from matplotlib.backends.backend_agg import FigureCanvasAgg

    if dpi:
        fig.set_dpi(dpi)  # lay out as written
    if not hasattr(fig.canvas, "get_renderer"):
        FigureCanvasAgg(fig)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    canvas = fig.bbox
    ticks = {id(t) for tick in fig.findobj(Tick) for t in (tick.label1, tick.label2)}
    texts = [t for t in fig.findobj(Text) if id(t) not in ticks and t.get_visible()
             and t.get_text().strip()]
    for ax in fig.axes:
        texts += _drawn_tick_labels(ax)
    legends = [lg for lg in fig.findobj(Legend) if lg.get_visible()]
    owner = {id(t): i for i, lg in enumerate(legends) for t in lg.get_texts()}
    if legends and any(lg.get_title().get_text() for lg in legends):
        owner.update({id(lg.get_title()): i for i, lg in enumerate(legends)})
    boxes = [(t, t.get_window_extent(renderer)) for t in texts]
    problems = []

    def name(t):
        return repr(t.get_text()[:40])

    def inside(box):
        return (box.x0 >= canvas.x0 - 0.5 and box.y0 >= canvas.y0 - 0.5
                and box.x1 <= canvas.x1 + 0.5 and box.y1 <= canvas.y1 + 0.5)

    def overlap(a, b, tol=0.5):
        return (a.x0 < b.x1 - tol and b.x0 < a.x1 - tol
                and a.y0 < b.y1 - tol and b.y0 < a.y1 - tol)

    scale = (dpi or fig.dpi) / 72.0
    for i, (t, box) in enumerate(boxes):
        if not inside(box):
            problems.append(f"text {name(t)} outside the canvas: {box.bounds} of "
                            f"{canvas.bounds}")
        if t.get_fontsize() * scale < MIN_PIXELS:
            problems.append(f"text {name(t)} is {t.get_fontsize() * scale:.1f} px high "
                            f"(< {MIN_PIXELS})")
        for u, other in boxes[i + 1:]:
            if overlap(box, other):
                problems.append(f"texts {name(t)} and {name(u)} overlap")
    for i, lg in enumerate(legends):
        box = lg.get_window_extent(renderer)
        if not inside(box):
            problems.append(f"legend {i} outside the canvas: {box.bounds} of {canvas.bounds}")
        for t, tbox in boxes:
            if owner.get(id(t)) != i and overlap(box, tbox):
                problems.append(f"legend {i} covers text {name(t)}")
    return problems


@pytest.fixture
def saved(monkeypatch):
    """[(Figure, dpi)] of every figure saved while the test runs (the saving still happens)."""
    from matplotlib.figure import Figure

    figures = []
    original = Figure.savefig

    def savefig(self, *args, **kwargs):
        figures.append((self, kwargs.get("dpi") or self.dpi))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", savefig)
    return figures


def _check(saved, expected: int):
    assert len(saved) == expected
    for fig, dpi in saved:
        assert layout_problems(fig, dpi) == []


def test_the_check_catches_a_planted_overlap_an_escape_and_a_tiny_label():
    """The control: two texts on top of each other, one off the canvas, one 4 px high and a
    legend over a text are each reported; the same figure without them passes."""
    from matplotlib.figure import Figure

    def figure(planted: bool):
        fig = Figure(figsize=(4, 3), dpi=100)
        ax = fig.add_subplot()
        ax.plot([0, 1], [0, 1], label="line")
        ax.set_title("a title")
        ax.text(0.2, 0.5, "first label", transform=ax.transAxes, fontsize=10)
        if planted:
            ax.text(0.25, 0.5, "second label", transform=ax.transAxes, fontsize=10)
            fig.text(0.95, 0.5, "off the canvas", fontsize=10)
            ax.text(0.2, 0.2, "tiny", transform=ax.transAxes, fontsize=3)
            ax.text(0.6, 0.85, "under the legend", transform=ax.transAxes, fontsize=10)
            ax.legend(loc="upper right")
        return fig

    assert layout_problems(figure(False)) == []
    problems = "\n".join(layout_problems(figure(True)))
    assert "'first label' and 'second label' overlap" in problems
    assert "'off the canvas' outside the canvas" in problems
    assert "'tiny' is 4.2 px high" in problems
    assert "covers text 'under the legend'" in problems


def _grid_panels():
    """A P-MO2G-like episode, and the panels experiments.gridworld.figures draws of it: the
    executed path over the expert's, then two plans (seen cells, path, goal, sub-goal)."""
    grid = np.zeros((16, 16), int)
    grid[1, 4], grid[2, 5], grid[1, 5], grid[8, 3] = 15, 2, 1, 12  # neighbours, labels
    grid[5:7, 9] = -1
    agent, reference, target = np.array([1, 1]), np.array([2, 5]), np.array([1, 5])
    expert = np.zeros((16, 16), bool)
    expert[1, 1:6] = True
    executed = np.array([[1, c] for c in range(1, 6)])
    seen = np.zeros((16, 16), bool)
    seen[:8, :8] = True
    plan = -np.ones((16, 16, 3))
    plan[1, 1:6, 0] = 1
    plan[1, 5, 1] = plan[2, 5, 2] = 1
    cells = dict(grid=grid, target=target, reference=reference)
    return [dict(cells, agent=agent, path=expert, path_label="expert path", executed=executed,
                 title="executed: 4 moves, success")] + [
        dict(cells, agent=executed[t], seen=seen, path=plan[..., 0], path_label="planned path",
             goal=plan[..., 1],
             subgoal=plan[..., 2], executed=executed[:t + 1], title=f"plan at move {t}")
        for t in (0, 2, 3, 4)]


INSTRUCTION = ("First, go to the carrot. Then, go east of it to find the apple, which lies "
               "somewhere past the tomato.")


def test_grid_world_figures(tmp_path, saved):
    """The grid-world episode figure (five panels, as the CLIs' --figures) and the export's
    one-panel figure: the instruction once, one legend inside the canvas, nothing overlapping,
    the object names in the legend."""
    from envs.gridworld import render

    panels = _grid_panels()
    render.episode_figure(tmp_path / "episode.png", panels, INSTRUCTION)
    render.render_episode(tmp_path / "one.png", **{k: v for k, v in panels[1].items()
                                                   if k not in ("title", "path_label")},
                          instruction=INSTRUCTION, title="export episode 0")
    _check(saved, 2)
    fig = saved[0][0]
    texts = [t.get_text() for t in fig.findobj(lambda a: hasattr(a, "get_text"))]
    assert sum("go to the carrot" in t for t in texts) == 1
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    for entry in ("agent", "expert path", "planned path", "goal estimate", "sub-goal", "target",
                  "reference", "executed", "not seen yet", "obstacle", "car = carrot",
                  "pep = pepper"):
        assert entry in legend


def test_top_down_block_figures(tmp_path, saved):
    """The Kuka world's top-down figure (a view before each placement and the end): one
    legend explains the base's "+", the shaded path, the pick and place frames, the stack
    digits and the blocks' colours."""
    from envs.kuka import render

    top = -np.ones((24, 24), int)
    height = np.zeros((24, 24), int)
    for block, (r, c) in enumerate(((3, 3), (3, 17), (18, 4), (18, 18))):
        top[r:r + 3, c:c + 3], height[r:r + 3, c:c + 3] = block, 1
    path = np.zeros((24, 24), bool)
    path[4, 4:19] = True
    stacked_top, stacked_height = top.copy(), height.copy()
    stacked_top[3:6, 17:20], stacked_height[3:6, 17:20] = 0, 2
    panels = [dict(top=top, height=height, path=path, goal=np.array([4, 18]),
                   pick=np.array([4, 4]), title="plan 1: red on green"),
              dict(top=stacked_top, height=stacked_height, title="end (1 placements)")]
    render.episode_figure(str(tmp_path / "kuka.png"), panels,
                          "Stack the red block on top of the green block. " * 3)
    _check(saved, 1)
    legend = " ".join(t.get_text() for t in saved[0][0].legends[0].get_texts())
    for entry in ("base", "path", "pick", "place", "stack", "red"):
        assert entry in legend


@pytest.mark.parametrize("calls", [(10.2, 10.9, 11.5, 12.1), (1.0, 30.0, 150.0, 900.0)])
def test_sweep_pareto_figures(tmp_path, saved, calls):
    """The sweep's Pareto figures, with the calls in a narrow range (log-axis labels used to
    pile up) and a wide one: no tick label, point label or legend overlaps another."""
    from experiments.sweeping.output import write_figures

    rows = [dict(task="gridworld/p_mo2g", modes=mode, num_steps=10, warm_num_steps=2,
                 warm_start_step=1, replan=replan, eta=0.0, language="canonical", SR=sr,
                 path_f1=f1, denoiser_calls_per_episode=c, seconds=s)
            for mode, replan, sr, f1, c, s in zip(
                ("warm_start", "warm_start", "on_the_fly", "on_the_fly"),
                ("on_change", "always", "on_refuted", "always"),
                (100.0, 100.0, 99.9, 100.0), (97.7, 98.0, 98.2, 98.9), calls,
                (20.0, 21.0, 24.0, 60.0))]
    write_figures(str(tmp_path), rows)
    assert len(saved) == 2
    assert [layout_problems(fig, dpi) for fig, dpi in saved] == [[], []]


@pytest.mark.parametrize("demos", [(100, 300, 1000), (100, 300, 1000, 3000, 10000)])
def test_babyai_sample_efficiency_figure(tmp_path, saved, demos):
    """The BabyAI success-against-demonstrations figure with the published numbers of
    demonstrations three decades past ours (its tick labels used to run together) and every
    published entry the level has: no text overlaps another or leaves the canvas."""
    from experiments.babyai.figures import sweep_figure
    from experiments.babyai.spec import published

    papers = published("goto") or [{"paper": "a paper", "table": "Table 3", "level": "goto",
                                     "demos": 341_100, "demos_high": 408_500, "success": 99.0,
                                     "what": "demos to reach 99%", "source": "-"}]
    rows = [{"demos": d, "SR": sr, "SR_ci95": [sr - 2.0, min(100.0, sr + 1.0)]}
            for d, sr in zip(demos, (62.0, 88.5, 97.2, 99.1, 99.6))]
    evaluation = {"demos": rows[-1]["demos"], "SR": 99.3}
    sweep_figure(str(tmp_path / "curve.png"), "goto", rows, evaluation, papers, 99.0)
    assert len(saved) == 1
    assert layout_problems(*saved[0]) == []
    ticks = [t.get_text() for t in saved[0][0].axes[0].get_xticklabels() if t.get_text()]
    assert "100k" in ticks and "100000" not in ticks  # compact labels past two decades
