"""The sample-efficiency figure: success (measured in minigrid) against the number of
demonstrations, log x axis, each point labelled with its SR where the label overlaps nothing
(``harness.plots``), the 99% line, the evaluation seeds' number of the fewest demos reaching
it, and the published numbers of demonstrations (vertical lines)."""
from __future__ import annotations

from experiments.harness.cli import atomic_file
from experiments.harness.plots import log_ticks, place_labels

DPI = 110


def sweep_figure(path: str, level: str, rows, evaluation, papers, target: float) -> str:
    """Writes the PNG of :func:`draw` (atomically) and returns its path."""
    fig = draw(level, rows, evaluation, papers, target)
    atomic_file(path, lambda tmp: fig.savefig(tmp, dpi=DPI, format="png"))
    return path


def draw(level: str, rows, evaluation, papers, target: float):
    """The figure (matplotlib Figure, laid out). rows: the validation rows (``demos``,
    ``SR``, ``SR_ci95``); evaluation: the evaluation row of the fewest reaching target, or
    None; papers: the level's published entries (``spec.PUBLISHED``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    xs = [r["demos"] for r in rows]
    ys = [r["SR"] for r in rows]
    low = [r["SR"] - r["SR_ci95"][0] for r in rows]
    high = [r["SR_ci95"][1] - r["SR"] for r in rows]
    fig = Figure(figsize=(6.4, 4.6), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    ax.errorbar(xs, ys, yerr=[low, high], color="#3060c0", marker="o", markersize=5,
                capsize=3, zorder=3, label="ours, validation seed (95% Wilson interval)")
    if evaluation is not None:
        ax.scatter([evaluation["demos"]], [evaluation["SR"]], marker="*", s=110,
                   color="#d04020", zorder=4, label="ours, evaluation seeds (the fewest "
                                                    f"reaching {target:g}%)")
    ax.axhline(target, color="0.4", linestyle="--", linewidth=0.9, label=f"{target:g}%")
    marks = xs + ([evaluation["demos"]] if evaluation is not None else [])
    for i, p in enumerate(x for x in papers if x.get("what") == "demos to reach 99%"):
        ax.axvline(p["demos"], color="#208040", linestyle=":", linewidth=1.2,
                   label=f"{p['paper']}, {p['table']}" if i == 0 else None)
        marks.append(p["demos"])
    ax.set_xscale("log")
    log_ticks(ax, marks)
    lo = min(ys + ([evaluation["SR"]] if evaluation is not None else []) + [target])
    ax.set_ylim(max(0.0, lo - 8.0), 101.5)
    ax.set_xlabel("training episodes (expert demonstrations)")
    ax.set_ylabel("success in minigrid (%)")
    ax.set_title(f"BabyAI {level}: success against demonstrations", fontsize=11)
    ax.grid(alpha=0.3)
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncol=2,
               fontsize=8, frameon=False)
    fig.canvas.draw()
    fig.set_layout_engine("none")  # the layout stays; labels are placed inside the axes
    place_labels(ax, xs, ys, [f"{y:.1f}" for y in ys], fig.canvas.get_renderer())
    return fig
