"""The batch's pictures: success rate against particle count, and ATE per log and method.

matplotlib's object API (Agg canvas, no pyplot state), as mcl3d.evaluation.plots. Each
function returns False, writing nothing, when the rows hold no data for its picture.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import StrMethodFormatter

from mcl3d.evaluation.run_plots import write_png

FIGURE_SIZE_IN = (10.0, 5.5)


def _figure() -> tuple[Figure, object]:
    fig = Figure(figsize=FIGURE_SIZE_IN, layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot(1, 1, 1)


def success_vs_particles(path: Path, rows: list[dict]) -> bool:
    """Per localize job, the share of runs judged a success at each particle count."""
    judged = [r for r in rows if r["command"] == "localize" and r.get("success") is not None
              and r["particles"] is not None]
    if not judged:
        return False
    fig, ax = _figure()
    for job in dict.fromkeys(r["job"] for r in judged):
        counts = sorted({r["particles"] for r in judged if r["job"] == job})
        rate, runs = [], []
        for n in counts:
            outcomes = [r["success"] for r in judged if r["job"] == job and r["particles"] == n]
            rate.append(100.0 * np.mean(outcomes))
            runs.append(len(outcomes))
        (line,) = ax.plot(counts, rate, "o-", lw=1.5, label=job)
        for n, y, k in zip(counts, rate, runs, strict=True):
            ax.annotate(f"{k}", (n, y), textcoords="offset points", xytext=(0, 6),
                        ha="center", fontsize="x-small", color=line.get_color())
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(StrMethodFormatter("{x:,.0f}"))
    ax.set(xlabel="particles", ylabel="success [%]", ylim=(-5, 105),
           title="localization: runs whose last scans are within tolerance of the truth "
                 "(numbers: runs)")
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.legend(loc="best", fontsize="small")
    write_png(path, fig)
    return True


def _ate_points(rows: list[dict]) -> list[tuple[str, str, float]]:
    """(log, method, ATE m) of every finished run; a SLAM run adds its odometry front-end."""
    points = []
    for r in rows:
        log = Path(r["log"]).stem
        if r.get("ate_m") is not None:
            points.append((log, r["job"], float(r["ate_m"])))
        if r.get("ate_odometry_m") is not None:
            points.append((log, f"{r['job']} (odometry front-end)", float(r["ate_odometry_m"])))
    return points


def ate_per_log(path: Path, rows: list[dict]) -> bool:
    """Every run's ATE (dots) and each method's median (bar) per log."""
    points = _ate_points(rows)
    if not points:
        return False
    logs = list(dict.fromkeys(p[0] for p in points))
    methods = list(dict.fromkeys(p[1] for p in points))
    width = 0.8 / len(methods)
    fig, ax = _figure()
    for j, method in enumerate(methods):
        colour, label = f"C{j % 10}", method
        for i, log in enumerate(logs):
            values = [p[2] for p in points if p[0] == log and p[1] == method]
            if not values:
                continue
            x = i - 0.4 + (j + 0.5) * width
            ax.bar(x, float(np.median(values)), width * 0.9, color=colour, alpha=0.35,
                   label=label)
            label = None  # one legend entry per method
            ax.plot(np.full(len(values), x), values, "o", ms=3, color=colour)
    ax.set_xticks(range(len(logs)), logs, rotation=30 if len(logs) > 4 else 0, ha="right"
                  if len(logs) > 4 else "center", fontsize="small")
    ax.set(ylabel="ATE translation RMSE [m]", ylim=(0, None),
           title="ATE per log and method (bars: median, dots: runs)")
    ax.grid(True, axis="y", lw=0.4, alpha=0.5)
    ax.legend(loc="best", fontsize="small")
    write_png(path, fig)
    return True

