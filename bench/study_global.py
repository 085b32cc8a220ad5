"""Study: success rate of global localization vs particle count, on seeded simulated logs.

For each world (office: ground robot; arena: drone; both with --height-band auto) and
seed, simulates a log (`mcl3d simulate`), builds its map from the world mesh
(`mcl3d build-map`), then runs `mcl3d localize --init global` with each particle count.
A run succeeds when the last `--tail` scans are all within 0.2 m and 3 deg of ground truth;
"scans to converge" is the first scan from which the error stays within that tolerance.
Prints a table and writes JSON.

    python bench/study_global.py --quick            # 2 seeds x office/arena, N = 10k, 30k
    python bench/study_global.py --seeds 10 --particles 10000 30000 100000 300000
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

TOL_M, TOL_DEG = 0.2, 3.0
WORLDS = {"office": ("ground", None), "arena": ("drone", None)}  # None: --height-band auto


def mcl3d(*args) -> None:
    subprocess.run([sys.executable, "-m", "mcl3d", *map(str, args)], check=True,
                   stdout=subprocess.DEVNULL)


def make_data(work: Path, world: str, seed: int, duration_s: float) -> tuple[Path, Path, Path]:
    log = work / f"{world}_{seed}.mcap"
    mesh = work / f"{world}_{seed}.ply"
    tsdf = work / f"{world}_{seed}.tsdf"
    if not log.exists():
        mcl3d("simulate", world, "-o", log, "--trajectory", WORLDS[world][0], "--duration",
              duration_s, "--seed", seed, "--export-mesh", mesh, "--force")
    if not tsdf.exists():
        mcl3d("build-map", mesh, "-o", tsdf, "--backend", "cpu", "--force")
    return log, tsdf, work / f"{world}_{seed}_gt.tum"


def scan_errors(out: Path, gt_tum: Path) -> tuple[np.ndarray, np.ndarray]:
    from mcl3d import geometry
    from mcl3d.trajectory import read_tum

    est = read_tum(out / "trajectory.tum")
    gt = read_tum(gt_tum)
    ok = (est.stamps_s >= gt.stamps_s[0]) & (est.stamps_s <= gt.stamps_s[-1])
    ref = gt.interpolate_poses(est.stamps_s[ok])
    d = np.linalg.norm(ref[:, :3, 3] - est.poses[ok, :3, 3], axis=1)
    a = np.degrees(geometry.rotation_angle(np.swapaxes(ref[:, :3, :3], 1, 2)
                                           @ est.poses[ok, :3, :3]))
    return d, a


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--worlds", nargs="+", default=list(WORLDS), choices=list(WORLDS))
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--particles", type=int, nargs="+",
                    default=[10_000, 30_000, 100_000, 300_000])
    ap.add_argument("--duration", type=float, default=20.0, help="simulated seconds per log")
    ap.add_argument("--max-scans", type=int, default=150)
    ap.add_argument("--tail", type=int, default=10, help="scans that must all be within "
                                                          "tolerance at the end")
    ap.add_argument("--quick", action="store_true",
                    help="2 seeds, N = 10k and 30k, 12 s logs, 100 scans")
    ap.add_argument("--work", type=Path, default=Path("/tmp/mcl3d-study"))
    ap.add_argument("--json", type=Path, default=Path("study_global.json"))
    args = ap.parse_args()
    if args.quick:
        args.seeds, args.particles, args.duration, args.max_scans = 2, [10_000, 30_000], 12.0, 100
    args.work.mkdir(parents=True, exist_ok=True)
    runs = []
    for world in args.worlds:
        for seed in range(1, args.seeds + 1):
            log, tsdf, gt = make_data(args.work, world, seed, args.duration)
            for n in args.particles:
                out = args.work / f"{world}_{seed}_{n}"
                band = WORLDS[world][1]
                t0 = time.perf_counter()
                mcl3d("localize", log, "--map", tsdf, "-o", out, "--particles", n, "--seed",
                      seed, "--max-scans", args.max_scans, "--backend", "cpu", "--force",
                      *(["--height-band", band] if band else []))
                d, a = scan_errors(out, gt)
                run = {"world": world, "seed": seed, "particles": n, "scans": len(d),
                       "wall_s": time.perf_counter() - t0, **evaluate_run(d, a, args.tail)}
                runs.append(run)
                print(json.dumps(run), flush=True)
    rows = []
    for world in args.worlds:
        for n in args.particles:
            rs = [r for r in runs if r["world"] == world and r["particles"] == n]
            conv = [r["scans_to_converge"] for r in rs if r["success"]]
            rows.append({"world": world, "particles": n, "runs": len(rs),
                         "success_rate": sum(r["success"] for r in rs) / max(len(rs), 1),
                         "median_scans_to_converge": float(np.median(conv)) if conv else None,
                         "median_rmse_after_m": float(np.median(
                             [r["rmse_after_m"] for r in rs if r["success"]])) if conv else None})
    from rich.console import Console
    from rich.table import Table

    table = Table(title="Global localization: success (within 0.2 m and 3 deg at the end)")
    for col in ("world", "particles", "runs", "success", "scans to converge (median)",
                "RMSE after (median)"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(r["world"], f"{r['particles']:,}", str(r["runs"]),
                      f"{100 * r['success_rate']:.0f} %",
                      "-" if r["median_scans_to_converge"] is None
                      else f"{r['median_scans_to_converge']:.0f}",
                      "-" if r["median_rmse_after_m"] is None
                      else f"{r['median_rmse_after_m']:.3f} m")
    Console().print(table)
    args.json.write_text(json.dumps({"settings": {k: str(v) for k, v in vars(args).items()},
                                     "summary": rows, "runs": runs}, indent=2))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
