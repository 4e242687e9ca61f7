"""Figure helpers shared by the experiments' plots (matplotlib, no pyplot): 1-2-5 ticks on a
log axis, and names placed beside their points where they overlap nothing (the sweep's Pareto
figures, the BabyAI sample-efficiency curve)."""
from __future__ import annotations

import numpy as np


def compact(v: float) -> str:
    """A tick's number in few characters: 500, 2k, 150k, 1M, 0.5."""
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(v) >= scale:
            return f"{v / scale:g}{suffix}"
    return f"{v:g}"


def log_ticks(ax, values) -> None:
    """Major ticks of a log x axis, labelled compactly (:func:`compact`), no minor labels
    (which pile up when the values span less than a decade): at 1, 2, 5 x 10^k when the
    values span at most two decades, at the powers of ten (every second one past six decades)
    when they span more, so that labels never run together; where fewer than two such ticks
    fall inside the values' range, four evenly spaced (in log) rounded ticks instead."""
    from matplotlib import ticker

    lo, hi = min(values), max(values)
    ax.set_xlim(lo / 1.25, hi * 1.25)
    decades = np.log10(hi / lo) if lo > 0 else 0.0
    subs = (1.0, 2.0, 5.0) if decades <= 2 else (1.0,)
    ax.xaxis.set_major_locator(ticker.LogLocator(base=10, subs=subs,
                                                 numticks=4 if decades > 6 else 12))
    ax.xaxis.set_minor_formatter(ticker.NullFormatter())
    ax.xaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _: compact(v)))
    inside = [t for t in ax.xaxis.get_major_locator().tick_values(lo / 1.25, hi * 1.25)
              if lo / 1.25 <= t <= hi * 1.25]
    if len(inside) < 2:
        ax.xaxis.set_major_locator(ticker.FixedLocator(sorted(
            {float(f"{v:.2g}") for v in np.geomspace(lo / 1.2, hi * 1.2, 4)})))


def overlaps(box, boxes, pad: float) -> bool:
    return any(box.x0 < b.x1 + pad and b.x0 < box.x1 + pad and box.y0 < b.y1 + pad
               and b.y0 < box.y1 + pad for b in boxes)


def place_labels(ax, xs, ys, names, renderer) -> None:
    """Each point's name beside it, where it covers no other name, no point and stays inside
    the axes: the first free place of eight directions at growing distances (a grey leader
    from a far one to its point); a name that finds none is replaced by its number in the
    printed table (its #), placed the same way."""
    from matplotlib.transforms import Bbox

    frame = ax.get_window_extent(renderer)
    points = [Bbox.from_extents(px - 4, py - 4, px + 4, py + 4)
              for px, py in ax.transData.transform(np.column_stack([xs, ys]))]
    placed = []
    offsets = [(dx * r, dy * r) for r in (6, 14, 24, 36)
               for dx, dy in ((1, 1), (1, -1), (-1, 1), (-1, -1), (1, 0), (-1, 0), (0, 1),
                              (0, -1))]
    for i in np.argsort(xs):
        for text in (names[i], str(i + 1)):
            fits = None
            for dx, dy in offsets:
                note = ax.annotate(text, (xs[i], ys[i]), xytext=(dx, dy), fontsize=7.5,
                                   textcoords="offset points", va="center",
                                   ha="left" if dx > 0 else "right" if dx < 0 else "center")
                box = note.get_window_extent(renderer)
                if frame.contains(box.x0, box.y0) and frame.contains(box.x1, box.y1) and \
                        not overlaps(box, placed, 5.0) and not overlaps(box, points, 0.0):
                    fits = note
                    break
                note.remove()
            if fits is not None:
                placed.append(box)
                if max(abs(dx), abs(dy)) > 6:  # a leader from a far name to its point
                    px, py = ax.transData.transform((xs[i], ys[i]))
                    k = renderer.points_to_pixels(1.0)
                    end = ax.transData.inverted().transform((px + 0.8 * dx * k,
                                                             py + 0.8 * dy * k))
                    ax.plot([xs[i], end[0]], [ys[i], end[1]], color="0.55", linewidth=0.6,
                            zorder=1)
                break
