"""Pictures of a run, written beside its outputs: `localize.png` and `slam.png`.

Each is the trajectory over the map's top view, the error against the log's ground truth
over time (when it has one) and the filter's health over time (ESS, hypotheses, ...), for
people who would rather look than read scans.csv or frames.csv. matplotlib's object API
(Agg canvas, no pyplot state), as `plots.py`; the map is drawn as a 2-D histogram of its
points, so big maps cost one pass over their points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator, NullFormatter, StrMethodFormatter

from mcl3d.core.errors import Mcl3dError
from mcl3d.core.geometry import se3_inverse
from mcl3d.core.outputs import atomic_open
from mcl3d.evaluation.metrics import PoseErrors, ate, evaluate
from mcl3d.io.trajectory import Trajectory

LOCALIZE_PICTURE = "localize.png"  # the file names, in the run's output folder
SLAM_PICTURE = "slam.png"
PICTURE_DPI = 100
FIGURE_SIZE_IN = (13.0, 7.5)  # 1300 x 750 pixels at PICTURE_DPI
MAP_CELLS = 600  # the top view's map histogram has at most this many cells on its long side
STATE_COLOURS = {"initializing": "tab:orange", "ambiguous": "tab:purple",
                 "converged": "tab:green", "lost": "tab:red"}


def write_png(path: Path, fig: Figure) -> None:
    """The figure as a PNG, atomically."""
    with atomic_open(Path(path), "wb") as f:
        fig.savefig(f, format="png", dpi=PICTURE_DPI)


def localize_figure(results, map_points: np.ndarray, gt: Trajectory | None,
                    map_cell_m: float) -> Figure:
    """`localize`'s picture: the estimate over the map coloured by filter state (and the
    ground truth), then error, ESS / particles and hypotheses / match ratio over time.

    `results` are the run's `LocalizationResult`s, `map_points` (n, 3) map-frame points of
    the map's surface (`map_cell_m` apart, its voxel size), `gt` the log's ground truth in
    the map frame, or None."""
    stamps = np.array([r.stamp_s for r in results])
    xyz = np.stack([r.T_map_lidar[:3, 3] for r in results])
    errors = _errors_at(gt, stamps, np.stack([r.T_map_lidar for r in results]))
    fig, top, panels = _layout(3 if errors is not None else 2)
    _draw_map(top, map_points, map_cell_m)
    if gt is not None:
        top.plot(gt.positions()[:, 0], gt.positions()[:, 1], "-", color="0.2", lw=1.2,
                 label="ground truth")
    top.plot(xyz[:, 0], xyz[:, 1], "-", color="tab:blue", lw=0.8, alpha=0.6, label="estimate")
    states = np.array([r.state.value for r in results])
    for state, colour in STATE_COLOURS.items():
        on = states == state
        if on.any():
            top.plot(xyz[on, 0], xyz[on, 1], "o", ms=3, color=colour, label=state)
    _finish_top(top, f"localize: {len(results)} scans over the map")
    t = stamps - stamps[0]
    rows = iter(panels)
    if errors is not None:
        _draw_errors(next(rows), [(errors, "estimate", "tab:blue")], stamps[0])
    health = next(rows)
    health.plot(t, [r.ess for r in results], "-", color="tab:blue", lw=1.0, label="ESS")
    health.plot(t, [r.n_particles for r in results], "--", color="0.4", lw=1.0,
                label="particles")
    _finish_panel(health, "particles", "effective sample size", log=True)
    fit = next(rows)
    fit.plot(t, [r.match_ratio for r in results], "-", color="tab:green", lw=1.0,
             label="match ratio")
    fit.set_ylim(0.0, 1.0)
    hyp = fit.twinx()
    hyp.step(t, [len(r.hypotheses) for r in results], where="post", color="tab:purple",
             lw=1.0, label="hypotheses")
    hyp.set_ylabel("hypotheses")
    hyp.set_ylim(bottom=0)
    hyp.yaxis.set_major_locator(MaxNLocator(integer=True))
    _finish_panel(fit, "share of scan points on a surface", "scan fit and hypotheses",
                  twin=hyp, xlabel=f"time since first scan ({stamps[0]:.3f} s) [s]")
    return fig


def slam_figure(frames, trajectories: dict[str, Trajectory], map_points: np.ndarray,
                gt: Trajectory | None, particles: int, map_cell_m: float) -> Figure:
    """`slam`'s picture: the SLAM and odometry trajectories over the keyframe map (and the
    ground truth, SE(3)-aligned into the map's frame), then their errors, ESS / hypotheses and
    loop particles / pruned particles per scan.

    `frames` are the run's records (`SlamFrames`), `trajectories` its "slam" and "odometry" ones,
    `map_points` (n, 3) world-frame points of the map (`map_cell_m` apart, its voxel size),
    `particles` the configured count."""
    slam, odom = trajectories["slam"], trajectories["odometry"]
    evals = _slam_evaluations(gt, slam, odom)
    fig, top, panels = _layout(3 if evals else 2)
    _draw_map(top, map_points, map_cell_m)
    if evals:
        gt_in_map = se3_inverse(evals["slam"].alignment.T_ref_est) @ gt.poses
        top.plot(gt_in_map[:, 0, 3], gt_in_map[:, 1, 3], "-", color="0.2", lw=1.2,
                 label="ground truth (SE(3)-aligned)")
    top.plot(odom.positions()[:, 0], odom.positions()[:, 1], "-", color="tab:orange", lw=1.0,
             label="odometry only")
    top.plot(slam.positions()[:, 0], slam.positions()[:, 1], "-", color="tab:blue", lw=1.2,
             label="SLAM")
    _finish_top(top, f"slam: {len(frames)} scans over the keyframe map")
    t0 = slam.stamps_s[0]
    t = slam.stamps_s - t0
    rows = iter(panels)
    if evals:
        _draw_errors(next(rows), [(evals["slam"].ate, "SLAM", "tab:blue"),
                                  (evals["odometry"].ate, "odometry only", "tab:orange")], t0)
    health = next(rows)
    health.plot(t, frames.ess, "-", color="tab:blue", lw=1.0, label="ESS")
    health.axhline(particles, ls="--", color="0.4", lw=1.0, label="particles")
    health.step(t, frames.hypotheses, where="post", color="tab:purple", lw=1.0,
                label="hypotheses")
    _finish_panel(health, "particles", "effective sample size and hypotheses", log=True)
    loops = next(rows)
    loops.step(t, frames.looping, where="post", color="tab:green", lw=1.0,
               label="particles seeing a loop")
    loops.step(t, frames.pruned, where="post", color="tab:red", lw=1.0,
               label="particles pruned")
    loops.set_ylim(0, 1.1 * max(1, int(frames.looping.max()), int(frames.pruned.max())))
    loops.yaxis.set_major_locator(MaxNLocator(integer=True))
    _finish_panel(loops, "particles per scan", "loops and pruning",
                  xlabel=f"time since first scan ({t0:.3f} s) [s]")
    return fig


def _layout(rows: int) -> tuple[Figure, object, list]:
    """The top view on the left, `rows` time panels sharing their time axis on the right."""
    fig = Figure(figsize=FIGURE_SIZE_IN, layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(rows, 2, width_ratios=[1.1, 1.0])
    top = fig.add_subplot(grid[:, 0])
    panels = [fig.add_subplot(grid[0, 1])]
    panels += [fig.add_subplot(grid[i, 1], sharex=panels[0]) for i in range(1, rows)]
    return fig, top, panels


def _draw_map(ax, points: np.ndarray, min_cell_m: float) -> None:
    """The map's points as a grey x-y histogram, darker where more surface stands above a
    cell (walls and trees over floors); cells a whole number of the points' spacing."""
    xy = np.asarray(points, dtype=np.float64).reshape(-1, 3)[:, :2]
    if len(xy) == 0:
        return
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    spacing = max(min_cell_m, 1e-3)  # a whole number of spacings per cell: no moire
    cell = spacing * max(1.0, np.ceil(float((hi - lo).max()) / MAP_CELLS / spacing))
    bins = np.floor((hi - lo) / cell).astype(int) + 1
    start = lo - 0.5 * cell  # points on a grid of `cell` fall in the middle of their bins
    counts, xs, ys = np.histogram2d(xy[:, 0], xy[:, 1], bins=bins,
                                    range=[[start[0], start[0] + bins[0] * cell],
                                           [start[1], start[1] + bins[1] * cell]])
    shown = np.ma.masked_equal(counts.T, 0)
    ax.imshow(shown, origin="lower", extent=(xs[0], xs[-1], ys[0], ys[-1]), cmap="Greys",
              norm=LogNorm(vmin=1, vmax=max(float(counts.max()), 2.0)), interpolation="nearest",
              alpha=0.6)


def _finish_top(ax, title: str) -> None:
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="x [m]", ylabel="y [m]", title=title)
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.legend(loc="best", fontsize="small", markerscale=2)


def _finish_panel(ax, ylabel: str, title: str, *, log: bool = False, twin=None,
                  xlabel: str | None = None) -> None:
    if log:
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(StrMethodFormatter("{x:g}"))
        ax.yaxis.set_minor_formatter(NullFormatter())
    ax.set(ylabel=ylabel, title=title)
    if xlabel is not None:
        ax.set_xlabel(xlabel)
    ax.grid(True, lw=0.4, alpha=0.5)
    handles, labels = ax.get_legend_handles_labels()
    if twin is not None:
        more = twin.get_legend_handles_labels()
        handles, labels = handles + more[0], labels + more[1]
    ax.legend(handles, labels, loc="best", fontsize="small")


def _draw_errors(ax, series: list[tuple[PoseErrors, str, str]], t0: float) -> None:
    """Translation error (solid, left axis) and rotation error (dotted, right axis)."""
    rot = ax.twinx()
    for errors, label, colour in series:
        t = errors.stamps_s - t0
        ax.plot(t, errors.translation_errors_m, "-", color=colour, lw=1.0,
                label=f"{label} ({errors.translation_m.rmse:.3f} m RMSE)")
        rot.plot(t, errors.rotation_errors_deg, ":", color=colour, lw=1.0,
                 label=f"{label} rotation")
    ax.set_ylim(bottom=0.0)
    rot.set_ylim(bottom=0.0)
    rot.set_ylabel("rotation error [deg] (dotted)")
    _finish_panel(ax, "translation error [m]", "error against ground truth", twin=rot)


def _errors_at(gt: Trajectory | None, stamps_s: np.ndarray, poses: np.ndarray
               ) -> PoseErrors | None:
    """Errors of map-frame poses against the ground truth at the same stamps (no alignment:
    both are in the map frame); None without ground truth over two of them."""
    if gt is None or len(gt) < 2:
        return None
    inside = (stamps_s >= gt.stamps_s[0]) & (stamps_s <= gt.stamps_s[-1])
    if inside.sum() < 2:
        return None
    return ate(gt.interpolate_poses(stamps_s[inside]), poses[inside], stamps_s[inside])


def _slam_evaluations(gt: Trajectory | None, slam: Trajectory, odom: Trajectory) -> dict:
    """SE(3)-aligned evaluations of "slam" and "odometry" (as the summary's ATE), or {}."""
    if gt is None or len(slam) < 3:
        return {}
    try:
        return {"slam": evaluate(gt, slam, alignment="se3"),
                "odometry": evaluate(gt, odom, alignment="se3")}
    except Mcl3dError:
        return {}
