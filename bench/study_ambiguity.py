"""Study: is global localization ever confidently wrong in look-alike worlds?

A user with a short-range view (the range gate at `--range` m, default 6) localizes globally
(100,000 particles by default) in worlds built of look-alike places: the office's row of
near-identical rooms, the near-symmetric arena, and the warehouse's identical rack aisles
(its one unique feature, a loading ramp, comes into view 62.5 s into the `ground` route).
Each run goes through `mcl3d.localization.pipeline.run`, the code behind `mcl3d localize`,
on the cpu backend; logs and maps (built from the world mesh) are cached under --work.

Per run, judged against ground truth:
- false convergence: scans the filter reported `converged` more than 1 m or 10 deg from the
  truth (the acceptance is zero, every world, every seed);
- the first scan reported `converged` within 0.2 m and 3 deg of the truth, and whether the
  run ends converged on the truth;
- in the warehouse, whether the truth was found after the ramp came into view.

Seeds: `--log-seeds` change the world's details, the path's oscillations and the sensor
noise (each has its own log and map); `--seeds` are the filter's seeds on each log.

    python bench/study_ambiguity.py --worlds warehouse office arena --seeds 1 2 3 4 5
    python bench/study_ambiguity.py --quick   # office and arena, seed 1, the first 20 s
    python bench/study_ambiguity.py --report bench/results/study_ambiguity.json
    python bench/study_ambiguity.py --worlds office --trajectory 'paper-office-{log_seed}' \
        --log-seeds 1 2 3 4 5 6 7 8 --seeds 1 --duration 90   # starts inside the rooms
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
WRONG_M, WRONG_DEG = 1.0, 10.0  # a `converged` claim this far off is a false convergence
TOL_M, TOL_DEG = 0.2, 3.0  # on the truth
# world -> (trajectory, log duration s, time the unique feature comes into view s or None)
WORLDS = {"warehouse": ("ground", 100.0, 62.5), "office": ("ground", 60.0, None),
          "arena": ("ground", 40.0, None)}


def mcl3d(*args) -> None:
    subprocess.run([sys.executable, "-m", "mcl3d", *map(str, args)], check=True,
                   stdout=subprocess.DEVNULL)


def route(world: str, log_seed: int, args) -> tuple[str, float, str]:
    """The log's trajectory, its duration (s) and its name: the world's own, or --trajectory
    with {log_seed} filled in (and --duration)."""
    trajectory, duration_s, _ = WORLDS[world]
    if args.trajectory is None:
        return trajectory, duration_s, f"{world}_{log_seed}"
    trajectory = args.trajectory.format(log_seed=log_seed)
    return trajectory, args.duration or duration_s, f"{world}_{log_seed}_{trajectory}"


def make_data(work: Path, world: str, log_seed: int, args) -> tuple[Path, Path, Path]:
    """The log and its map from the world mesh (cached)."""
    trajectory, duration_s, name = route(world, log_seed, args)
    log = work / f"{name}.mcap"
    mesh = work / f"{world}_{log_seed}.ply"
    tsdf = work / f"{world}_{log_seed}.tsdf"
    if not log.exists():
        mcl3d("simulate", world, "-o", log, "--trajectory", trajectory, "--duration",
              duration_s, "--seed", log_seed, "--export-mesh", mesh, "--force")
    if not tsdf.exists():
        mcl3d("build-map", mesh, "-o", tsdf, "--backend", "cpu", "--force")
    return log, tsdf, work / f"{name}_gt.tum"


def scan_errors(out: Path, gt_tum: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per scan: stamp (s from the first), position error (m), rotation error (deg)."""
    from mcl3d.core import geometry
    from mcl3d.io.trajectory import read_tum

    est = read_tum(out / "trajectory.tum")
    gt = read_tum(gt_tum)
    ref = gt.interpolate_poses(est.stamps_s)
    d = np.linalg.norm(ref[:, :3, 3] - est.poses[:, :3, 3], axis=1)
    a = np.degrees(geometry.rotation_angle(np.swapaxes(ref[:, :3, :3], 1, 2)
                                           @ est.poses[:, :3, :3]))
    return est.stamps_s - gt.stamps_s[0], d, a


def judge(t_s: np.ndarray, d: np.ndarray, a: np.ndarray, states: list[str],
          feature_s: float | None) -> dict:
    """The study's figures for one run (see the module docstring)."""
    converged = np.array([s == "converged" for s in states])
    wrong = converged & ((d > WRONG_M) | (a > WRONG_DEG))
    on_truth = converged & (d < TOL_M) & (a < TOL_DEG)
    first = int(np.argmax(on_truth)) if on_truth.any() else None
    out = {"scans": len(d), "converged_scans": int(converged.sum()),
           "false_converged_scans": int(wrong.sum()),
           "false_convergence_rate": float(wrong.sum() / max(converged.sum(), 1)),
           "first_converged_on_truth_s": None if first is None else round(float(t_s[first]), 2),
           "ends_converged_on_truth": bool(on_truth[-1]),
           "final_state": states[-1], "final_error_m": round(float(d[-1]), 3),
           "states": {s: states.count(s) for s in sorted(set(states))}}
    if feature_s is not None:
        after = on_truth & (t_s >= feature_s)
        out["found_after_feature"] = bool(after.any() and on_truth[-1])
        out["feature_s"] = feature_s
    return out


def run_one(work: Path, world: str, log_seed: int, seed: int, args) -> dict:
    from mcl3d.localization.pipeline import LocalizeConfig, LocalizeRequest, run

    log, tsdf, gt_tum = make_data(work, world, log_seed, args)
    trajectory, _, name = route(world, log_seed, args)
    out = work / f"run_{name}_{seed}_{args.particles}"
    cfg = LocalizeConfig.model_validate({"max_scans": args.max_scans or None, "localizer": {
        "particles": args.particles, "seed": seed,
        "sensor": {"max_range_m": args.range}}})
    t0 = time.perf_counter()
    res = run(LocalizeRequest(log, tsdf, out, cfg, force=True, backend="cpu"))
    wall_s = time.perf_counter() - t0
    t_s, d, a = scan_errors(out, gt_tum)
    states = [str(r.state) for r in res.results]
    feature_s = WORLDS[world][2] if args.trajectory is None else None
    return {"world": world, "trajectory": trajectory, "log_seed": log_seed, "seed": seed,
            "particles": args.particles, "range_m": args.range, "wall_s": round(wall_s, 1),
            "ms_per_update": round(res.summary.ms_per_update["total"], 1),
            "claim_checks": res.claim_checks,
            **judge(t_s, d, a, states, feature_s)}


def report(runs: list[dict]) -> None:
    print(f"{'world':10} {'log':>3} {'seed':>4} {'conv':>5} {'false':>5} {'truth at s':>10} "
          f"{'end on truth':>12} {'after feature':>13}")
    for r in runs:
        print(f"{r['world']:10} {r['log_seed']:>3} {r['seed']:>4} {r['converged_scans']:>5} "
              f"{r['false_converged_scans']:>5} {r['first_converged_on_truth_s']!s:>10} "
              f"{r['ends_converged_on_truth']!s:>12} "
              f"{r.get('found_after_feature', '-')!s:>13}")
    false = sum(r["false_converged_scans"] for r in runs)
    print(f"false-converged scans over {len(runs)} runs: {false}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", nargs="+", default=list(WORLDS), choices=list(WORLDS))
    ap.add_argument("--log-seeds", nargs="+", type=int, default=[1])
    ap.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3, 4, 5])
    ap.add_argument("--particles", type=int, default=100_000)
    ap.add_argument("--range", type=float, default=6.0, help="range gate (m)")
    ap.add_argument("--trajectory", help="the logs' route instead of the world's own; "
                    "{log_seed} is replaced by the log seed, e.g. paper-office-{log_seed}: the "
                    "office tours that start inside look-alike rooms (log seeds 1-8)")
    ap.add_argument("--duration", type=float, help="seconds of each --trajectory log")
    ap.add_argument("--max-scans", type=int, default=0, help="stop each run after this "
                    "many scans (0: the whole log)")
    ap.add_argument("--quick", action="store_true",
                    help="office and arena, log and filter seed 1, the first 200 scans")
    ap.add_argument("--work", type=Path, default=RESULTS / "study_ambiguity")
    ap.add_argument("--json", type=Path, default=RESULTS / "study_ambiguity.json")
    ap.add_argument("--report", nargs="+", type=Path, help="print the table of these files")
    args = ap.parse_args()
    if args.report:
        report([r for f in args.report for r in json.loads(f.read_text())["runs"]])
        return
    if args.quick:
        args.worlds, args.log_seeds, args.seeds, args.max_scans = ["office", "arena"], [1], [1], 200
    from mcl3d.core import runtime

    runtime.init("cpu")
    args.work.mkdir(parents=True, exist_ok=True)
    runs: list[dict] = []
    for world in args.worlds:
        for log_seed in args.log_seeds:
            for seed in args.seeds:
                runs.append(run_one(args.work, world, log_seed, seed, args))
                args.json.parent.mkdir(parents=True, exist_ok=True)
                args.json.write_text(json.dumps({"runs": runs}, indent=1))
                print(json.dumps(runs[-1]), flush=True)
    report(runs)


if __name__ == "__main__":
    main()
