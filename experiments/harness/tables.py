"""Result tables as text, shared by every experiment and benchmark CLI: a row table that ends
with a legend of its columns, the per-seed rates with their pooled 95% intervals, and the
per-phrasing rates of rows that mix phrasings. Pure functions of result rows (the dicts the
JSON files hold)."""
from __future__ import annotations

import textwrap

LEGEND_WIDTH = 100
"""Columns of a legend line (it wraps, continuation lines indented)."""


def legend(entries, title: str = "legend") -> str:
    """A legend under a table: "legend: name = meaning; ..." for each (name, meaning) pair,
    wrapped at LEGEND_WIDTH columns; '' for no entries."""
    text = "; ".join(f"{name} = {meaning}" for name, meaning in entries)
    return "\n".join(textwrap.wrap(f"{title}: {text}", LEGEND_WIDTH, subsequent_indent="  ",
                                   break_on_hyphens=False)) if text else ""


def format_table(rows, columns, legend_entries=(), row_names=()) -> str:
    """A plain-text table of result rows; columns: (key, format, header) triples or (key,
    format, header, meaning) quadruples, the first left-aligned (widened to its longest value);
    missing values shown as '-'. It ends with its legend: the columns' meanings, then
    legend_entries' (name, meaning) pairs (e.g. "Prec/Rec/F1"), and a "rows:" line of
    row_names' pairs (what the row names mean, e.g. the flag value of each)."""
    widths = [len(c[1].format(0 if i else "")) for i, c in enumerate(columns)]
    first = columns[0][0]
    widths[0] = max([widths[0]] + [len(str(row.get(first, ""))) for row in rows])
    head = " ".join(c[2].rjust(w) if i else c[2].ljust(w)
                    for i, (c, w) in enumerate(zip(columns, widths)))
    lines = [head, "-" * len(head)]
    for row in rows:
        cells = [str(row.get(first, "-")).ljust(widths[0])]
        cells += [c[1].format(row[c[0]]) if row.get(c[0]) is not None else "-".rjust(w)
                  for c, w in zip(columns[1:], widths[1:])]
        lines.append(" ".join(cells))
    entries = [(c[2], c[3]) for c in columns if len(c) > 3 and c[3]] + list(legend_entries)
    lines += [text for text in (legend(entries), legend(row_names, "rows")) if text]
    return "\n".join(lines)


def format_intervals(rows, seeds, width: int) -> str:
    """Per-seed SR and the pooled 95% intervals, one line per row (and SR_ordered's where a row
    has its interval)."""
    lines = [f"SR per seed ({', '.join(map(str, seeds))}) and 95% interval of the pooled SR:"]
    width = max([width] + [len(r["method"]) for r in rows])
    for row in rows:
        per = " / ".join(f"{row['per_seed'][str(s)]['SR']:.1f}" for s in seeds)
        lo, hi = row["SR_ci95"]
        extra = ""
        if "SR_ordered_ci95" in row:
            olo, ohi = row["SR_ordered_ci95"]
            per_o = " / ".join(f"{row['per_seed'][str(s)]['SR_ordered']:.1f}" for s in seeds)
            extra = f"; SR_ordered {per_o} [{olo:.2f}, {ohi:.2f}]"
        lines.append(f"  {row['method']:<{width}} {per} [{lo:.2f}, {hi:.2f}]{extra}")
    return "\n".join(lines)


def format_phrasings(rows, unit: str = "episodes") -> str:
    """One line per row that mixes phrasings (its ``per_phrasing``): SR (/ SR_ordered) of each
    template (#index) over its own episodes, or constraints with ``unit="constraints"`` (the
    Kuka world), and how many, so a phrasing the planner misreads shows; '' when no row mixes
    phrasings."""
    def rate(p):
        return f"{p['SR']:.1f}" + (f"/{p['SR_ordered']:.1f}" if "SR_ordered" in p else "")

    lines = [f"  {row['method']}: " + " ".join(
        f"#{p['template']} {rate(p)} ({p[unit]})" for p in row["per_phrasing"])
        for row in rows if "per_phrasing" in row]
    return (f"per phrasing, SR (/ ordered) ({unit}):\n" + "\n".join(lines)) if lines else ""
