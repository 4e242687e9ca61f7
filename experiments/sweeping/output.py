"""What a sweep writes: the printed table, CSV, and the Pareto figures (success against cost)."""
from __future__ import annotations

import csv
import os

import numpy as np

from experiments.harness.plots import log_ticks, place_labels
from experiments.harness.tables import legend

CSV_FIELDS = ("task", "setting", "modes", "num_steps", "eta", "warm_num_steps",
              "warm_start_step", "noise", "replan", "multi", "language", "carry", "psi",
              "follow_mark", "samples", "denoiser",
              "seed", "episodes", "checkpoint", "reader", "SR", "SR_ordered", "SR_diffuser", "GD",
              "path_precision", "path_recall", "path_f1", "SPL", "fallback_percent",
              "settle_changed", "denoiser_calls_per_episode", "seconds", "compile_seconds",
              "wall_seconds", "devices")


def write_csv(path: str, rows) -> None:
    """The rows as CSV: the columns of CSV_FIELDS that some row has."""
    fields = [k for k in CSV_FIELDS if any(k in r for r in rows)]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: row.get(k, "") for k in fields})


def pareto_front(xs, ys) -> list[int]:
    """Indices of the points no other point beats (lower x and higher y), by increasing x."""
    order = sorted(range(len(xs)), key=lambda i: (xs[i], -ys[i]))
    front, best = [], -np.inf
    for i in order:
        if ys[i] > best:
            front.append(i)
            best = ys[i]
    return front


def label(row) -> str:
    """A configuration (or its row) in a few words."""
    if row["task"].startswith("kuka/"):
        return (f"{row['task'].split('/')[1]} {row['modes']} {row['num_steps']}"
                + (" multi" if row["multi"] else "")
                + (f" {row['language']}" if row["language"] != "canonical" else "")
                + (" arc" if row["carry"] == "arc" else ""))
    extra = (f" {row['warm_num_steps']}/{row['warm_start_step']}" if row["modes"] ==
             "warm_start" else f" {row['num_steps']}")
    return (f"{row['modes']}{extra}"
            + (f" {row['replan']}" if row["replan"] in ("on_change", "on_refuted") else "")
            + (f" eta{row['eta']:g}" if row["eta"] else "")
            + (f" {row['language']}" if row.get("language", "canonical") != "canonical"
               else "")
            + (f" follow>{row['follow_mark']:g}" if row.get("psi") == "follow" else "")
            + (f" best of {row['samples']}" if row.get("samples", 1) > 1 else "")
            + (" posterior" if row.get("denoiser") == "posterior" else ""))


FIGURE_DPI = 110
SECOND_PANELS = (("path_f1", "path F1 (%)"), ("SR_diffuser", "SR, Diffuser's check (%)"))
"""The right panel: the first of these that every row has (none: SR alone)."""


def write_figures(out_dir: str, rows) -> list[str]:
    """Two PNGs (x: denoiser calls per episode, then evaluation seconds), each with SR and
    (grid world) path F1 / (Kuka) Diffuser's SR against the cost, every configuration
    labelled (by its number in the printed table where its name does not fit), the Pareto
    front drawn (when every SR ties, as on P-MO2G, the path F1 panel still separates the
    modes); one legend and the title inside the canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    os.makedirs(out_dir, exist_ok=True)
    panels = [("SR", "SR (%)")] + [p for p in SECOND_PANELS
                                   if all(p[0] in r for r in rows)][:1]
    names = [label(r) for r in rows]
    paths = []
    for x_key, x_label, name in (("denoiser_calls_per_episode", "denoiser calls per episode",
                                  "pareto_calls.png"),
                                 ("seconds", "seconds (evaluation, no compilation)",
                                  "pareto_seconds.png")):
        xs = [r[x_key] for r in rows]
        # Laid out at the dpi it is written with: text widths do not scale with the dpi.
        fig = Figure(figsize=(6.2 * len(panels), 5.0), dpi=FIGURE_DPI, layout="constrained")
        FigureCanvasAgg(fig)
        axes = fig.subplots(1, len(panels), squeeze=False)[0]
        for ax, (y_key, y_label) in zip(axes, panels):
            ys = [r[y_key] for r in rows]
            ax.scatter(xs, ys, color="#3060c0", zorder=3, s=18,
                       label="a configuration: its name, or its # in the printed table")
            front = pareto_front(xs, ys)
            ax.plot([xs[i] for i in front], [ys[i] for i in front], color="#d04020",
                    zorder=2, marker="o", markerfacecolor="none", label="Pareto front")
            ax.set_xscale("log")
            log_ticks(ax, xs)
            ax.set_xlabel(x_label)
            ax.set_ylabel(y_label)
            lo, hi = min(ys), max(ys)
            pad = max(0.5, 0.15 * (hi - lo))
            ax.set_ylim(lo - pad, hi + pad)
            ax.grid(alpha=0.3)
        fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncol=2,
                   fontsize=8.5, frameon=False)
        fig.suptitle(f"success against cost ({len(rows)} configurations)", fontsize=11)
        fig.canvas.draw()
        fig.set_layout_engine("none")  # the layout stays; names are placed inside the axes
        renderer = fig.canvas.get_renderer()
        for ax, (y_key, _) in zip(axes, panels):
            place_labels(ax, xs, [r[y_key] for r in rows], names, renderer)
        path = os.path.join(out_dir, name)
        fig.savefig(path, dpi=FIGURE_DPI)
        paths.append(path)
    return paths


def format_rows(rows) -> str:
    """The printed table: one line per configuration (a rate a world lacks shows nan)."""
    head = (f"{'#':>3} {'configuration':<34} {'seed':>5} {'eps':>5} {'SR':>7} {'SR_ord':>7} "
            f"{'F1':>6} {'SPL':>6} {'calls':>7} {'sec':>7} {'compile':>7}")
    lines = [head, "-" * len(head)]
    nan = float("nan")
    for i, r in enumerate(rows):
        lines.append(f"{i + 1:>3} {label(r):<34} {r['seed']:>5} {r['episodes']:>5} "
                     f"{r['SR']:>7.2f} {r.get('SR_ordered', nan):>7.2f} "
                     f"{r.get('path_f1', nan):>6.1f} {r.get('SPL', nan):>6.3f} "
                     f"{r['denoiser_calls_per_episode']:>7.1f} "
                     f"{r['seconds']:>7.1f} {r['compile_seconds']:>7.1f}")
    return "\n".join(lines + [legend(LEGEND)])


LEGEND = (
    ("configuration", "the planning mode, denoising steps (warm_start: schedule/start step), then "
                      "what differs from the CLIs' defaults (trigger, eta, phrasing, psi, plans "
                      "drawn; Kuka: task, mode, steps, column, phrasing, carry)"),
    ("eps", "episodes"),
    ("SR", "success rate, % (grid: of episodes; Kuka: strict, of instructed constraints)"),
    ("SR_ord", "% of episodes that stood on the reference first"),
    ("F1", "executed cells against the expert path's, %"), ("SPL", "0-1"),
    ("calls", "denoiser calls per episode"),
    ("sec", "wall seconds of the evaluation, compilation not included (in the Kuka world the "
            "first configuration's also compiles the settling step)"),
    ("compile", "seconds compiling its program (0: reused from an earlier configuration)"),
    ("nan", "a rate the world lacks"))
"""The printed table's legend (experiments.harness.tables.legend)."""
