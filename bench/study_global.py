"""Study: success rate of global localization vs particle count, on seeded simulated logs.

For each world and seed, `mcl3d simulate` writes a log (office: ground robot on the `ground`
route; arena: drone on the `drone` route; the seed changes the world's furniture jitter and
the arena's stage and crate, the path's oscillations and every sensor noise; the route, and
so the start, is the world's: office at the corridor's west end, arena in the crate corner)
and `mcl3d build-map` builds the map from the world mesh, both once (when first needed) and
cached under --work. Each particle count then runs the real `mcl3d localize` pipeline
(`mcl3d.localization.pipeline.run`: cpu backend, `--init global`, `--height-band auto`,
filter seed = log seed) in this process, so Taichi starts once; the grids a global search
derives from a map are cached beside it (MapCache).

Success criterion (honest, judged against ground truth, never against the filter's own
state): the estimate of each of the last `--tail` scans of the run is within 0.2 m and 3 deg
of ground truth. A run ends at `--max-scans` (20 s of the log: the office robot has driven
along the corridor into the first room, the drone across the hall), or earlier once the
filter has reported `converged` for `--stable` consecutive scans (it then tracks; tracking
is tested not to diverge). A filter that locked onto a look-alike place and says so is a
failure, and so is one still searching at the end. "Scans to converge" is the first scan
from which the error stays within tolerance until the end of the run (the filter's own
`converged` state comes later: it waits for motion, see docs/sensor-model.md).

Kidnap recovery (--kidnap SEEDS): the office `kidnap` trajectory (the robot is carried 24 m
at half the log; odometry does not see it) tracked from the first ground-truth pose, on the
whole office's map at 10 cm, as in tests/test_localize_sim.py but over several seeds. A
recovery succeeds when the filter says `converged` within 0.2 m and 3 deg of the truth after
the jump and stays within tolerance to the end of the log.

Writes JSON after every run (--json), so a partial study still reports what finished, and
prints a table (success rate and median scans to converge per world x particle count).
Runs are ordered by particle count, smallest first, so the expensive counts come last.

    python bench/study_global.py --quick            # 2 seeds x office/arena, N = 10k, 30k
    python bench/study_global.py                    # seeds 1-10, N = 10k ... 300k
    python bench/study_global.py --report a.json b.json   # the table of finished runs
    python bench/study_global.py --kidnap 0 1 2 3 4 --json bench/results/study_kidnap.json

`--preset NAME` runs every localization with the named settings of `mcl3d localize --preset`
(mcl3d/localization/presets.py; `paper`: the MCL paper's model, initialization, resampling
and estimate) instead of the defaults; runs, table rows and run folders carry the name.

The paper's own setting: `--map-source log` localizes in a map built by `mcl3d build-map`
from another log of the world (not from the mesh; `odometry-log`: at its odometry's
poses), `--sensor os0-64` simulates the arena's lidar, and `--sigma S` makes the odometry
ground truth plus white noise of S on velocity and angular velocity, as the paper's sweep
(0.1 in its arena):

    python bench/study_global.py --worlds arena --sensor os0-64 --sigma 0.1 --preset paper

The paper's office experiment, 11 trajectories in one world on one map: `--trajectory
paper-office-{seed} --world-seed 1 --seeds 1 2 ... 11` (each tour starts in a look-alike room,
the corridor or the open area; `mcl3d simulate office --trajectory paper-office-K`).
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

TOL_M, TOL_DEG = 0.2, 3.0
WRONG_M, WRONG_DEG = 1.0, 10.0  # a `converged` claim this far off is a false convergence
WORLDS = {"office": "ground", "arena": "drone"}
MAPPING_ROUTES = {"office": ("survey", 325.0), "arena": ("loop", 140.0)}  # once round, s


def mcl3d(*args) -> None:
    subprocess.run([sys.executable, "-m", "mcl3d", *map(str, args)], check=True,
                   stdout=subprocess.DEVNULL)


def log_config(work: Path, sigma: float | None) -> list:
    """`--config` of a simulated log whose odometry is the MCL paper's: ground truth plus
    white noise of sigma on the velocity and angular velocity (m/s, rad/s), nothing else."""
    if sigma is None:
        return []
    cfg = work / f"odometry_sigma_{sigma:g}.yaml"
    cfg.write_text(f"odometry:\n  trans_noise: 0\n  rot_noise_per_m: 0\n"
                   f"  rot_noise_per_rad: 0\n  scale_error_sigma: 0\n  turn_bias_sigma: 0\n"
                   f"  velocity_noise: [{sigma}, {sigma}]\n")
    return ["--config", cfg]


def trajectory(world: str, seed: int, args) -> str:
    """The localized log's route: the world's own, or --trajectory with {seed} filled in."""
    return WORLDS[world] if args.trajectory is None else args.trajectory.format(seed=seed)


def world_seed(seed: int, args) -> int:
    return seed if args.world_seed is None else args.world_seed


def variant_tag(world: str, seed: int, args) -> str:
    """Names a log/run by what differs from the study's original setting."""
    tag = "" if args.trajectory is None else f"_{trajectory(world, seed, args)}"
    tag += "" if args.world_seed is None else f"_w{args.world_seed}"
    tag += "" if args.sensor is None else f"_{args.sensor}"
    return tag if args.sigma is None else f"{tag}_sigma{args.sigma:g}"


def make_data(work: Path, world: str, seed: int, args) -> tuple[Path, Path, Path]:
    """The seed's log and map (cached: simulated and built once)."""
    name = f"{world}_{seed}{variant_tag(world, seed, args)}"
    wseed = world_seed(seed, args)
    log, mesh = work / f"{name}.mcap", work / f"{world}_{wseed}.ply"
    sensor = [] if args.sensor is None else ["--sensor", args.sensor]
    if not log.exists():
        mcl3d("simulate", world, "-o", log, "--trajectory", trajectory(world, seed, args),
              "--duration", args.duration, "--seed", seed, "--world-seed", wseed,
              "--export-mesh", mesh, *sensor, *log_config(work, args.sigma), "--force")
    if args.map_source == "mesh":
        tsdf = work / f"{world}_{wseed}.tsdf"
        if not tsdf.exists():
            mcl3d("build-map", mesh, "-o", tsdf, "--backend", "cpu", "--force")
    else:
        tsdf = map_from_log(work, world, wseed, args)
    return log, tsdf, work / f"{name}_gt.tum"


def map_from_log(work: Path, world: str, seed: int, args) -> Path:
    """A map from a log: `mcl3d build-map` over another log of the same world (the same
    `--world-seed`, so the same furniture; once round a route that sees every room, with its
    own seed, so other noise: the paper, too, mapped with other trajectories than it
    localized on), at the log's true poses (`log`, what
    build-map does by default) or at the poses of `mcl3d odometry` on it, anchored at its
    first true pose so the map shares the world's frame (`odometry-log`: a robot's map)."""
    from mcl3d.io.trajectory import Trajectory, read_tum, write_tum

    sensor_tag = "" if args.sensor is None else f"_{args.sensor}"
    name = f"{world}_{seed}_mapping{sensor_tag}"
    tsdf = work / f"{name}_{args.map_source}.tsdf"
    if tsdf.exists():
        return tsdf
    log = work / f"{name}.mcap"
    sensor = [] if args.sensor is None else ["--sensor", args.sensor]
    route, duration_s = MAPPING_ROUTES[world]
    if not log.exists():
        mcl3d("simulate", world, "-o", log, "--trajectory", route, "--duration", duration_s,
              "--seed", seed + 1000, "--world-seed", seed, *sensor, "--force")
    poses = []
    if args.map_source == "odometry-log":
        mcl3d("odometry", log, "-o", work / f"{name}_odometry", "--backend", "cpu", "--force")
        odo = read_tum(work / f"{name}_odometry" / "odometry.tum")
        T_map_first = read_tum(work / f"{name}_gt.tum").interpolate_poses(odo.stamps_s[:1])[0]
        poses = ["--trajectory", work / f"{name}_odometry_poses.tum"]
        write_tum(poses[1], Trajectory(odo.stamps_s, T_map_first @ odo.poses))
    mcl3d("build-map", log, "-o", tsdf, *poses, "--backend", "cpu", "--force")
    return tsdf


KIDNAP_STD = [0.05, 0.05, 0.02, *np.degrees([0.01, 0.01, 0.02]).tolist()]  # test's spread (m, deg)


def make_kidnap_data(work: Path, seed: int, duration_s: float) -> tuple[Path, Path, Path]:
    log = work / f"kidnap_{seed}.mcap"
    mesh = work / f"kidnap_{seed}.ply"
    tsdf = work / f"kidnap_{seed}.tsdf"
    if not log.exists():
        mcl3d("simulate", "office", "-o", log, "--trajectory", "kidnap", "--duration",
              duration_s, "--seed", seed, "--export-mesh", mesh, "--force")
    if not tsdf.exists():
        mcl3d("build-map", mesh, "-o", tsdf, "--voxel-size", 0.1, "--backend", "cpu",
              "--force")
    return log, tsdf, work / f"kidnap_{seed}_gt.tum"


def kidnap_once(work: Path, seed: int, args, cache: MapCache) -> dict:
    """One kidnap run: detection, re-seeding and the scan of the recovery."""
    from mcl3d.io.trajectory import read_tum
    from mcl3d.localization.pipeline import LocalizeConfig, LocalizeRequest, run

    log, tsdf, gt_tum = make_kidnap_data(work, seed, args.kidnap_duration)
    cache.current = tsdf
    out = work / f"kidnap_{seed}_{args.kidnap_particles}"
    cfg = LocalizeConfig.model_validate({"localizer": {
        "particles": args.kidnap_particles, "seed": seed,
        "init": {"mode": "gt", "std": KIDNAP_STD}}})
    t0 = time.perf_counter()
    res = run(LocalizeRequest(log, tsdf, out, cfg, force=True, backend="cpu"))
    wall = time.perf_counter() - t0
    d, a = scan_errors(out, gt_tum)
    gt = read_tum(gt_tum)
    jump = int(np.argmax(np.linalg.norm(np.diff(gt.poses[:, :3, 3], axis=0), axis=1) > 5.0)) + 1
    states = [r.state for r in res.results]
    good = (d < TOL_M) & (a < TOL_DEG)
    back = [k for k in range(jump, len(d)) if states[k] == "converged" and good[k]]
    recovered = bool(back) and bool(good[back[0]:].all())
    lost = [k for k in range(jump, len(d)) if states[k] == "lost"]
    reseeds = [(k, r.reseeded) for k, r in enumerate(res.results) if r.reseeded]
    return {"seed": seed, "particles": args.kidnap_particles, "scans": len(d),
            "jump_scan": jump, "tracked_before": bool(good[:jump].all()),
            "lost_detected_after": lost[0] - jump if lost else None,
            "reseeds": reseeds, "recovered": recovered,
            "scans_to_recover": back[0] - jump if recovered else None,
            "final_error_m": float(d[-1]), "final_state": states[-1],
            "wall_s": round(wall, 1)}


def scan_errors(out: Path, gt_tum: Path) -> tuple[np.ndarray, np.ndarray]:
    from mcl3d.core import geometry
    from mcl3d.io.trajectory import read_tum

    est = read_tum(out / "trajectory.tum")
    gt = read_tum(gt_tum)
    ok = (est.stamps_s >= gt.stamps_s[0]) & (est.stamps_s <= gt.stamps_s[-1])
    ref = gt.interpolate_poses(est.stamps_s[ok])
    d = np.linalg.norm(ref[:, :3, 3] - est.poses[ok, :3, 3], axis=1)
    a = np.degrees(geometry.rotation_angle(np.swapaxes(ref[:, :3, :3], 1, 2)
                                           @ est.poses[ok, :3, :3]))
    return d, a


def tracking_rmse(d: np.ndarray, filter_converged_at: int | None) -> float | None:
    """Translation RMSE from the scan the filter itself declared converged (the issue's
    'after convergence' accuracy), None when it never did."""
    if filter_converged_at is None or filter_converged_at >= len(d):
        return None
    return float(np.sqrt(np.mean(d[filter_converged_at:] ** 2)))


def evaluate_run(d: np.ndarray, a: np.ndarray, tail: int) -> dict:
    good = (d < TOL_M) & (a < TOL_DEG)
    success = bool(len(good) >= tail and good[-tail:].all())
    bad = np.flatnonzero(~good)
    converge = (int(bad[-1]) + 1 if len(bad) else 0) if success else None
    after = good.copy()
    if converge is not None:
        after[:converge] = False
    rmse = float(np.sqrt(np.mean(d[after] ** 2))) if after.any() else None
    return {"success": success, "scans_to_converge": converge, "rmse_after_m": rmse,
            "final_error_m": float(d[-1]), "final_error_deg": float(a[-1])}


class MapCache:
    """The grids a global search derives from a map (free-space candidates, the coarse
    distance field) depend only on the map file and the config: computed once per map and
    kept beside it as .npz, so every particle count and a re-run reuse them. Installed by
    wrapping the two functions the Localizer calls; `current` names the map being run."""

    def __init__(self):
        import mcl3d.localization.coarse_field
        import mcl3d.localization.localizer

        self.current: Path | None = None
        self._free = mcl3d.localization.localizer.free_cells
        self._coarse = mcl3d.localization.coarse_field.coarse_field
        mcl3d.localization.localizer.free_cells = self.free_cells
        mcl3d.localization.coarse_field.coarse_field = self.coarse_field

    def _path(self, kind: str, cfg) -> Path:
        import hashlib

        key = hashlib.sha1(cfg.model_dump_json().encode()).hexdigest()[:10]
        return self.current.with_name(f"{self.current.stem}_{kind}_{key}.npz")

    def free_cells(self, tsdf, cfg):
        from mcl3d.localization.initialization import FreeCells

        path = self._path("free", cfg)
        if path.exists():
            z = np.load(path)
            return FreeCells(z["corners_m"], float(z["cell_m"]))
        cells = self._free(tsdf, cfg)
        np.savez(path, corners_m=cells.corners_m, cell_m=cells.cell_m)
        return cells

    def coarse_field(self, tsdf, cfg):
        import dataclasses

        from mcl3d.localization.coarse_field import CoarseField

        path = self._path("coarse", cfg)
        if path.exists():
            z = np.load(path)
            return CoarseField(**{f.name: z[f.name].item() if z[f.name].ndim == 0 else z[f.name]
                                  for f in dataclasses.fields(CoarseField)})
        f = self._coarse(tsdf, cfg)
        np.savez_compressed(path, **{x.name: getattr(f, x.name)
                                     for x in dataclasses.fields(CoarseField)})
        return f


class StopWhenStable:
    """on_progress callback: interrupts the run (Ctrl-C semantics: outputs are kept) once
    the filter reported `converged` for `stable` scans in a row."""

    def __init__(self, stable: int):
        self.stable = stable
        self.run = 0
        self.states: list[str] = []

    def __call__(self, progress) -> None:
        state = progress.status.split()[0]  # the filter state, then the match ratio
        self.states.append(state)
        self.run = self.run + 1 if state == "converged" else 0
        if self.run >= self.stable:
            raise KeyboardInterrupt


def localize_once(log: Path, tsdf: Path, out: Path, n: int, seed: int, args) -> dict:
    from mcl3d.core import config as config_mod
    from mcl3d.core.errors import RunInterrupted
    from mcl3d.localization.pipeline import LocalizeConfig, LocalizeRequest, run
    from mcl3d.localization.presets import localize_preset

    cfg = config_mod.load(LocalizeConfig, None, {
        "max_scans": args.max_scans, "localizer.particles": n, "localizer.seed": seed,
        "localizer.init.mode": "global"}, preset=localize_preset(args.preset))
    stop = StopWhenStable(args.stable)
    t0 = time.perf_counter()
    try:
        run(LocalizeRequest(log, tsdf, out, cfg, force=True, backend="cpu", preset=args.preset),
            on_progress=stop)
        stopped_early = False
    except RunInterrupted:
        stopped_early = True
    summary = json.loads((out / "summary.json").read_text())
    return {"wall_s": round(time.perf_counter() - t0, 1), "stopped_early": stopped_early,
            "filter_converged_at_scan": summary["converged_at_scan"],
            "ms_per_update": round(summary["ms_per_update"]["total"], 1),
            "claim_checks": summary.get("claim_checks"), "states": stop.states}


def setting(run: dict) -> str:
    """The map, the lidar, the odometry and the routes of a run (older JSON: mesh, VLP-16,
    simulated wheel odometry, the world's own route)."""
    sigma = run.get("odometry_sigma")
    odometry = "wheel odometry" if sigma is None else f"truth + sigma {sigma:g}"
    route = "" if run.get("routes") is None else f", {run['routes']}"
    return f"{run.get('map', 'mesh')} map, {run.get('sensor', 'vlp16')}, {odometry}{route}"


def summarize(runs: list[dict], worlds, particles) -> list[dict]:
    rows = []
    presets = sorted({r.get("preset", "default") for r in runs})
    settings = sorted({setting(r) for r in runs})
    for preset, sett, world, n in ((p, s, w, n) for p in presets for s in settings
                                   for w in worlds for n in particles):
        rs = [r for r in runs if r["world"] == world and r["particles"] == n
              and r.get("preset", "default") == preset and setting(r) == sett]
        if not rs:
            continue
        ok = [r for r in rs if r["success"]]
        claimed = [r["rmse_after_filter_converged_m"] for r in ok  # right, never claimed:
                   if r["rmse_after_filter_converged_m"] is not None]  # no tracking RMSE
        rows.append({
            "preset": preset, "setting": sett, "world": world, "particles": n, "runs": len(rs),
            "success_rate": len(ok) / len(rs),
            "median_scans_to_converge": float(np.median([r["scans_to_converge"]
                                                         for r in ok])) if ok else None,
            "median_rmse_after_m": float(np.median([r["rmse_after_m"] for r in ok]))
            if ok else None,
            "median_tracking_rmse_m": float(np.median(claimed)) if claimed else None,
            "median_ms_per_update": float(np.median([r["ms_per_update"] for r in rs]))})
    return rows


def print_table(rows: list[dict]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="Global localization: success = last scans within 0.2 m and 3 deg")
    for col in ("preset", "setting", "world", "particles", "runs", "success",
                "scans to converge (median)", "RMSE from then (median)",
                "RMSE once filter converged", "ms/update (median)"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(r.get("preset", "default"), r["setting"], r["world"], f"{r['particles']:,}",
                      str(r["runs"]),
                      f"{100 * r['success_rate']:.0f} %",
                      "-" if r["median_scans_to_converge"] is None
                      else f"{r['median_scans_to_converge']:.0f}",
                      "-" if r["median_rmse_after_m"] is None
                      else f"{r['median_rmse_after_m']:.3f} m",
                      "-" if r["median_tracking_rmse_m"] is None
                      else f"{r['median_tracking_rmse_m']:.3f} m",
                      f"{r['median_ms_per_update']:.0f}")
    Console().print(table)


def write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=2))
    tmp.replace(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--worlds", nargs="+", default=list(WORLDS), choices=list(WORLDS))
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 11)),
                    help="log/filter seeds")
    ap.add_argument("--particles", type=int, nargs="+",
                    default=[10_000, 30_000, 100_000, 300_000])
    ap.add_argument("--duration", type=float, default=24.0, help="simulated seconds per log")
    ap.add_argument("--max-scans", type=int, default=200)
    ap.add_argument("--stable", type=int, default=15,
                    help="stop a run after this many consecutive 'converged' scans")
    ap.add_argument("--tail", type=int, default=10,
                    help="scans that must all be within tolerance at the end of a run")
    ap.add_argument("--quick", action="store_true", help="seeds 1 2, N = 10k and 30k")
    ap.add_argument("--preset", default="default",
                    help="named localize settings (mcl3d/localization/presets.py)")
    ap.add_argument("--map-source", choices=("mesh", "log", "odometry-log"), default="mesh",
                    help="the map from the world mesh, or built by `mcl3d build-map` from "
                    "another log of the world at its true poses or its odometry's")
    ap.add_argument("--sensor", help="simulated lidar (default: vlp16), e.g. os0-64 as the "
                    "paper's arena")
    ap.add_argument("--trajectory", help="the localized logs' route instead of the world's "
                    "own; {seed} is replaced by the log seed, e.g. paper-office-{seed}: the "
                    "MCL paper's 11 office trajectories with seeds 1-11")
    ap.add_argument("--world-seed", type=int, help="every log and map in this one world "
                    "(default: each log seed's own world)")
    ap.add_argument("--sigma", type=float,
                    help="odometry = ground truth + white noise of this sigma on velocity "
                    "and angular velocity (m/s, rad/s), as the paper's sweep")
    ap.add_argument("--report", type=Path, nargs="+",
                    help="only print the table of these JSON files' runs (merged)")
    ap.add_argument("--kidnap", type=int, nargs="+", metavar="SEED",
                    help="run the office kidnap recovery for these seeds instead")
    ap.add_argument("--kidnap-duration", type=float, default=8.0)
    ap.add_argument("--kidnap-particles", type=int, default=50_000)
    ap.add_argument("--tag", default="", help="appended to every run's folder name (a "
                    "variant of the code or settings beside earlier runs)")
    ap.add_argument("--work", type=Path, default=Path("bench/results/study_global"))
    ap.add_argument("--json", type=Path, default=Path("bench/results/study_global.json"))
    args = ap.parse_args()
    if args.report:
        runs = [r for path in args.report for r in json.loads(path.read_text())["runs"]]
        for r in runs:  # older JSON: recompute from the run's trajectory
            if "rmse_after_filter_converged_m" not in r:
                d, _ = scan_errors(args.work / f"{r['world']}_{r['seed']}_{r['particles']}",
                                   args.work / f"{r['world']}_{r['seed']}_gt.tum")
                r["rmse_after_filter_converged_m"] = tracking_rmse(
                    d, r["filter_converged_at_scan"])
        worlds = [w for w in WORLDS if any(r["world"] == w for r in runs)]
        print_table(summarize(runs, worlds, sorted({r["particles"] for r in runs})))
        return
    if args.quick:
        args.seeds, args.particles = [1, 2], [10_000, 30_000]
    args.work.mkdir(parents=True, exist_ok=True)
    from mcl3d.core import runtime

    info = runtime.init("cpu")
    cache = MapCache()
    settings = {k: str(v) for k, v in vars(args).items()}
    settings.update(machine=f"{platform.platform()}, {info.device}")
    runs: list[dict] = []
    if args.kidnap:
        for seed in args.kidnap:
            runs.append(kidnap_once(args.work, seed, args, cache))
            print(json.dumps(runs[-1]), flush=True)
            write_json(args.json, {"settings": settings, "runs": runs})
        ok = sum(r["recovered"] for r in runs)
        print(f"kidnap recovered in {ok}/{len(runs)}; wrote {args.json}")
        return
    for n in sorted(args.particles):
        for world in args.worlds:
            for seed in args.seeds:
                log, tsdf, gt = make_data(args.work, world, seed, args)
                cache.current = tsdf
                suffix = "" if args.preset == "default" else f"_{args.preset}"
                if args.map_source != "mesh":
                    suffix += f"_{args.map_source}"
                suffix += args.tag
                out = args.work / f"{world}_{seed}{variant_tag(world, seed, args)}_{n}{suffix}"
                timing = localize_once(log, tsdf, out, n, seed, args)
                d, a = scan_errors(out, gt)
                claimed = np.array([s == "converged" for s in timing.pop("states")][:len(d)])
                wrong = claimed & ((d[:len(claimed)] > WRONG_M) | (a[:len(claimed)] > WRONG_DEG))
                run = {"preset": args.preset, "world": world, "seed": seed, "particles": n,
                       "map": args.map_source, "sensor": args.sensor or "vlp16",
                       "odometry_sigma": args.sigma, "routes": args.trajectory,
                       "trajectory": trajectory(world, seed, args),
                       "world_seed": world_seed(seed, args),
                       "scans": len(d),
                       **timing, **evaluate_run(d, a, args.tail),
                       "rmse_after_filter_converged_m": tracking_rmse(
                           d, timing["filter_converged_at_scan"]),
                       "false_converged_scans": int(wrong.sum())}
                runs.append(run)
                print(json.dumps(run), flush=True)
                rows = summarize(runs, args.worlds, sorted(args.particles))
                write_json(args.json, {"settings": settings, "summary": rows, "runs": runs})
    print_table(summarize(runs, args.worlds, sorted(args.particles)))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
