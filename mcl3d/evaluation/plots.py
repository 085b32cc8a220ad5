"""Figures for `mcl3d eval`: top view of both trajectories and the error over time.

matplotlib is imported inside the functions (Agg canvas, no pyplot state), so importing
this module costs nothing and plotting works without a display.
"""

from __future__ import annotations

from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from mcl3d.core.errors import ConfigError
from mcl3d.core.outputs import atomic_open
from mcl3d.evaluation.metrics import Evaluation
from mcl3d.io.trajectory import Trajectory

PLOT_FORMATS = ("png", "pdf", "svg")


def plot_format(path: Path) -> str:
    """The image format named by the file suffix; checked before any work is done."""
    fmt = Path(path).suffix.lower().lstrip(".")
    if fmt not in PLOT_FORMATS:
        raise ConfigError(
            f"{path}: unknown image type {Path(path).suffix or '(no suffix)'}; "
            f"end the name with one of {', '.join('.' + f for f in PLOT_FORMATS)}", setting="plot")
    return fmt


def plot_evaluation(path: Path, evaluation: Evaluation, ref: Trajectory, est: Trajectory,
                    ref_label: str = "reference", est_label: str = "estimate") -> None:
    """Write a two-panel figure atomically: x-y top view (estimate aligned) and ATE over time."""
    fmt = plot_format(path)
    est_xyz = evaluation.alignment.apply(est.poses)[:, :3, 3]
    ref_xyz = ref.positions()
    fig = Figure(figsize=(12, 5), layout="constrained")
    FigureCanvasAgg(fig)
    top, err = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1, 1.3]})

    top.plot(ref_xyz[:, 0], ref_xyz[:, 1], "-", color="0.3", lw=1.5, label=ref_label)
    top.plot(est_xyz[:, 0], est_xyz[:, 1], "-", color="tab:blue", lw=1.0,
             label=f"{est_label} ({_alignment_text(evaluation)})")
    top.plot(ref_xyz[:1, 0], ref_xyz[:1, 1], "o", color="0.3", ms=5)
    top.set_aspect("equal", adjustable="datalim")
    top.set(xlabel="x [m]", ylabel="y [m]", title="top view")
    top.grid(True, lw=0.4, alpha=0.5)
    top.legend(loc="best", fontsize="small")

    ate = evaluation.ate
    t0 = ate.stamps_s[0]
    err.plot(ate.stamps_s - t0, ate.translation_errors_m, "-", color="tab:red", lw=1.0,
             label="translation error")
    stats = ate.translation_m
    err.axhline(stats.rmse, color="tab:red", ls="--", lw=0.8, label=f"RMSE {stats.rmse:.3f} m")
    err.axhline(stats.median, color="tab:orange", ls=":", lw=0.8,
                label=f"median {stats.median:.3f} m")
    err.set(xlabel=f"time since {t0:.3f} s [s]", ylabel="ATE translation [m]",
            title=f"absolute trajectory error ({len(evaluation.association)} poses)")
    err.set_ylim(bottom=0.0)
    err.grid(True, lw=0.4, alpha=0.5)
    rot = err.twinx()
    rot.plot(ate.stamps_s - t0, ate.rotation_errors_deg, "-", color="tab:green", lw=0.7,
             alpha=0.7, label="rotation error")
    rot.set_ylabel("ATE rotation [deg]")
    rot.set_ylim(bottom=0.0)
    lines = err.get_legend_handles_labels()
    more = rot.get_legend_handles_labels()
    err.legend(lines[0] + more[0], lines[1] + more[1], loc="upper left", fontsize="small")

    with atomic_open(Path(path), "wb") as f:
        fig.savefig(f, format=fmt, dpi=120)


def _alignment_text(evaluation: Evaluation) -> str:
    how = evaluation.alignment
    if how.method == "sim3":
        return f"sim3 aligned, scale {how.scale:.4f}"
    return "not aligned" if how.method == "none" else f"{how.method} aligned"

