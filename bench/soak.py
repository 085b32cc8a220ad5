"""Soak test: does memory stay flat over a long log? `localize`, `odometry` and `slam` run
as real subprocesses (the whole CLI command, one at a time) over a long simulated log while
this script samples each process's resident memory (RSS) once a second.

Data: `mcl3d simulate WORLD --trajectory loop --duration MINUTES*60` (the route repeats for
as long as asked) with a VLP-16 thinned to every --column-stride-th firing, and the world's
mesh built into a TSDF map with `mcl3d build-map`; both are cached in --work-dir and reused.
`localize` tracks from the first ground-truth pose.

Progress comes from the checkpoints the commands write every 30 s of wall time (the summary
marked `"checkpoint": true` holds the scans done), so no pipe or terminal is needed. Per
command the JSON records: RSS after the first minute of wall time and at the last checkpoint
(the end of the scan loop, before the final outputs are written), the growth between them in
% (target <= 5%), the growth over the window's second half (a one-time allocation, such as
the coarse map a global re-seed builds, shows in the first figure, a leak in both), the
slope of a line fitted to RSS over the window (MiB/min), the peak RSS (including writing the
outputs), scans/s in the loop and overall, and the whole series; a PNG of RSS over time per
command goes next to the JSON. On the cpu backend Taichi's fields
live in the process's heap, so RSS includes them (Taichi has no allocation counter that
another process can read).

    python bench/soak.py                                  # 30 min, all three commands
    python bench/soak.py --minutes 2 --commands odometry  # a quick look
    python bench/soak.py --json bench/results/soak.json --work-dir /tmp/soak
    python bench/soak.py --reanalyse --json bench/results/soak.json  # figures, PNGs again
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

COMMANDS = ("localize", "odometry", "slam")
SUMMARY_FILES = {"localize": "summary.json", "odometry": "odometry_summary.json",
                 "slam": "slam_summary.json"}
GROWTH_TARGET_PCT = 5.0
MIB = 1024.0 * 1024.0


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=30.0, help="log length (simulated min)")
    ap.add_argument("--commands", nargs="+", choices=COMMANDS, default=list(COMMANDS))
    ap.add_argument("--particles", type=int, default=5000, help="localize particles")
    ap.add_argument("--slam-particles", type=int, default=1000, help="slam particles")
    ap.add_argument("--world", default="office")
    ap.add_argument("--column-stride", type=int, default=16,
                    help="keep every n-th VLP-16 firing (16: ~1,800 points per scan)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--baseline-s", type=float, default=60.0,
                    help="memory 'after the first minute' is sampled this long after the start")
    ap.add_argument("--sample-s", type=float, default=1.0, help="RSS sampling period (s)")
    ap.add_argument("--work-dir", type=Path, default=Path("bench/results/soak_data"),
                    help="cached log and map, and the commands' outputs")
    ap.add_argument("--json", type=Path, default=Path("bench/results/soak.json"),
                    help="results; the PNGs go beside it")
    ap.add_argument("--reanalyse", action="store_true",
                    help="run nothing: recompute the figures and PNGs of --json's runs")
    return ap.parse_args(argv)


def mcl3d(*args: str) -> list[str]:
    return [sys.executable, "-m", "mcl3d", *args]


def ensure_data(args: argparse.Namespace) -> tuple[Path, Path]:
    """The simulated log and its TSDF map, made once per (minutes, stride, seed)."""
    work = args.work_dir
    work.mkdir(parents=True, exist_ok=True)
    stem = f"{args.world}_loop_{args.minutes:g}min_s{args.column_stride}_seed{args.seed}"
    log, mesh, tsdf = work / f"{stem}.mcap", work / f"{args.world}.ply", work / f"{stem}.tsdf"
    if not log.exists():
        cfg = work / f"{stem}_sim.yaml"
        cfg.write_text(f"lidar:\n  column_stride: {args.column_stride}\n")
        subprocess.run(mcl3d("simulate", args.world, "-o", str(log), "--trajectory", "loop",
                             "--duration", f"{args.minutes * 60:g}", "--seed", str(args.seed),
                             "--config", str(cfg), "--export-mesh", str(mesh), "--force"),
                       check=True, stdout=subprocess.DEVNULL)
    if not tsdf.exists():
        subprocess.run(mcl3d("build-map", str(mesh), "-o", str(tsdf), "--backend", "cpu",
                             "--force"), check=True, stdout=subprocess.DEVNULL)
    return log, tsdf


def command_line(name: str, log: Path, tsdf: Path, out: Path, args) -> list[str]:
    common = [str(log), "-o", str(out), "--backend", args.backend, "--force"]
    if name == "localize":
        return mcl3d("localize", *common, "--map", str(tsdf), "--init", "gt",
                     "--particles", str(args.particles), "--seed", str(args.seed))
    if name == "slam":
        return mcl3d("slam", *common, "--particles", str(args.slam_particles))
    return mcl3d("odometry", *common)


def rss_bytes(pid: int) -> int | None:
    """Resident memory of `pid` (psutil when installed, else /proc); None once it is gone."""
    try:
        import psutil
    except ImportError:
        try:
            status = Path(f"/proc/{pid}/status").read_text()
        except OSError:
            return None
        kib = [line.split()[1] for line in status.splitlines() if line.startswith("VmRSS:")]
        return int(kib[0]) * 1024 if kib else None
    try:
        return int(psutil.Process(pid).memory_info().rss)
    except psutil.Error:  # the process has ended
        return None


def read_summary(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None  # not written yet, or being replaced


def watch(cmd: list[str], out: Path, summary_name: str, sample_s: float) -> dict:
    """Run `cmd`, sampling RSS every `sample_s` and the scans done from its checkpoints."""
    if out.exists():
        shutil.rmtree(out)
    log_path = out.parent / f"{out.name}.stderr.txt"
    samples: list[tuple[float, float, int | None]] = []  # (t s, RSS MiB, scans or None)
    checkpoints: list[tuple[float, int]] = []  # (t s, scans) when a new checkpoint appeared
    last_mtime = None
    with open(log_path, "w") as err:
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err)
        while proc.poll() is None:
            t = time.monotonic() - t0
            rss = rss_bytes(proc.pid)
            scans = None
            summary_path = out / summary_name
            mtime = summary_path.stat().st_mtime if summary_path.exists() else None
            if mtime is not None and mtime != last_mtime:
                summary = read_summary(summary_path)
                if summary is not None and summary.get("checkpoint"):
                    scans = int(summary["scans"])
                    checkpoints.append((t, scans))
                    last_mtime = mtime
            if rss is not None:
                samples.append((t, rss / MIB, scans))
            time.sleep(max(0.0, sample_s - (time.monotonic() - t0 - t)))
        wall_s = time.monotonic() - t0
    final = read_summary(out / summary_name) or {}
    return {"command": " ".join(cmd), "returncode": proc.returncode, "wall_s": wall_s,
            "samples": samples, "checkpoints": checkpoints, "final_summary": final,
            "stderr_tail": Path(log_path).read_text()[-2000:]}


def analyse(run: dict, baseline_s: float) -> dict:
    """The figures of one run (see the module docstring)."""
    t = np.array([s[0] for s in run["samples"]])
    rss = np.array([s[1] for s in run["samples"]])
    ckpt = run["checkpoints"]
    scans = int(run["final_summary"].get("scans", 0))
    fig = {"scans": scans, "wall_s": round(run["wall_s"], 1), "peak_rss_mib": float(rss.max()),
           "scans_per_s_overall": scans / run["wall_s"], "checkpoints": len(ckpt)}
    if len(ckpt) >= 2:
        (ta, na), (tb, nb) = ckpt[0], ckpt[-1]
        fig["scans_per_s_loop"] = (nb - na) / (tb - ta)
    if not ckpt or ckpt[-1][0] <= baseline_s:
        fig["note"] = "the run ended before its first minute was over: no growth figure"
        return fig
    t_end = ckpt[-1][0]
    base = float(np.interp(baseline_s, t, rss))
    end = float(rss[np.searchsorted(t, t_end)])
    window = (t >= baseline_s) & (t <= t_end)
    slope = np.polyfit(t[window] / 60.0, rss[window], 1)[0] if window.sum() > 2 else 0.0
    done = [n for tc, n in ckpt if tc <= baseline_s]
    mid = float(np.interp((baseline_s + t_end) / 2, t, rss))
    fig.update({"rss_1min_mib": base, "rss_end_mib": end, "end_t_s": round(t_end, 1),
                "growth_second_half_pct": 100.0 * (end - mid) / mid,
                "scans_at_1min": done[-1] if done else 0, "scans_at_end": ckpt[-1][1],
                "growth_pct": 100.0 * (end - base) / base, "slope_mib_per_min": float(slope),
                "flat": 100.0 * (end - base) / base <= GROWTH_TARGET_PCT})
    return fig


def plot(name: str, run: dict, fig: dict, path: Path, baseline_s: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([s[0] for s in run["samples"]]) / 60.0
    rss = np.array([s[1] for s in run["samples"]])
    f, ax = plt.subplots(figsize=(8, 4))
    ax.plot(t, rss, lw=1.2, label="RSS")
    if "rss_1min_mib" in fig:
        ax.axvline(baseline_s / 60, color="grey", ls=":", label=f"{baseline_s:g} s")
        ax.axvline(fig["end_t_s"] / 60, color="grey", ls="--", label="last checkpoint")
        title = (f"{name}: {fig['scans']} scans, growth {fig['growth_pct']:+.1f}% "
                 f"after {baseline_s:g} s")
    else:
        title = f"{name}: {fig['scans']} scans"
    ax.set(xlabel="wall time (min)", ylabel="RSS (MiB)", title=title)
    ax.set_ylim(0, rss.max() * 1.1)
    ax2 = ax.twinx()
    ck = np.array(run["checkpoints"] or [(0, 0)], dtype=float)
    ax2.plot(ck[:, 0] / 60, ck[:, 1], "o", ms=3, color="tab:orange", label="scans done")
    ax2.set_ylabel("scans done (checkpoints)")
    lines = ax.get_legend_handles_labels()
    more = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + more[0], lines[1] + more[1], loc="lower center", fontsize=8, ncol=4)
    f.tight_layout()
    f.savefig(path, dpi=110)
    plt.close(f)


def machine() -> dict:
    model = next((line.split(":", 1)[1].strip() for line in
                  Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name")), platform.processor())
    return {"cpu": model, "cores": os.cpu_count(), "python": platform.python_version()}


def print_table(figures: dict) -> None:
    print(f"{'command':<10}{'scans':>7}{'wall s':>8}{'scans/s':>9}{'RSS 1min':>10}"
          f"{'RSS end':>9}{'growth':>8}{'2nd half':>9}{'MiB/min':>9}{'peak':>8}")
    for name, f in figures.items():
        if "growth_pct" not in f:
            print(f"{name:<10}{f['scans']:>7}{f['wall_s']:>8.0f}  {f.get('note', '')}")
            continue
        print(f"{name:<10}{f['scans']:>7}{f['wall_s']:>8.0f}"
              f"{f.get('scans_per_s_loop', 0):>9.1f}{f['rss_1min_mib']:>10.0f}"
              f"{f['rss_end_mib']:>9.0f}{f['growth_pct']:>7.1f}%"
              f"{f['growth_second_half_pct']:>8.1f}%"
              f"{f['slope_mib_per_min']:>9.2f}{f['peak_rss_mib']:>8.0f}")


def reanalyse(args: argparse.Namespace) -> int:
    report = json.loads(args.json.read_text())
    for name, run in report["runs"].items():
        run["figures"] = {**run["figures"], **analyse(run, args.baseline_s)}
        plot(name, run, run["figures"], Path(run["png"]), args.baseline_s)
    args.json.write_text(json.dumps(report, indent=1, default=str))
    print_table({n: r["figures"] for n, r in report["runs"].items()})
    return 0


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.reanalyse:
        return reanalyse(args)
    log, tsdf = ensure_data(args)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    report = {"machine": machine(), "log": str(log), "minutes": args.minutes,
              "column_stride": args.column_stride, "seed": args.seed, "runs": {}}
    if args.json.exists():  # keep the commands run earlier (one command at a time)
        previous = read_summary(args.json) or {}
        if previous.get("log") == str(log):
            report["runs"] = previous.get("runs", {})
    for name in args.commands:
        out = args.work_dir / f"out_{name}"
        run = watch(command_line(name, log, tsdf, out, args), out, SUMMARY_FILES[name],
                    args.sample_s)
        fig = analyse(run, args.baseline_s)
        if name == "slam":
            fig["slam_summary"] = {k: run["final_summary"].get(k) for k in
                                   ("keyframes", "warnings", "num_warnings")}
        png = args.json.with_name(f"{args.json.stem}_{name}.png")
        plot(name, run, fig, png, args.baseline_s)
        report["runs"][name] = {"figures": fig, "png": str(png), **run}
        args.json.write_text(json.dumps(report, indent=1, default=str))
        if run["returncode"] != 0:
            print(f"{name} exited {run['returncode']}:\n{run['stderr_tail']}", file=sys.stderr)
    print_table({n: r["figures"] for n, r in report["runs"].items()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
