"""The device suite's driver (run it through bench/device_suite.sh, which checks the GPU).

Runs the localize, bench_commands (the whole localize command), SLAM, batched GICP,
odometry and fusion benchmarks in that order on one backend, each a child process with its
JSON redirected to bench/results/device_suite/ (MCL3D_BENCH_RESULTS), each under a time cap
that keeps the whole suite within `--budget-s`; then merges them with the device's name and
the papers' targets into bench/results/device_suite.json (cuda) or
device_suite_<backend>.json (a smoke test, which run_all does not render as cuda).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from results_io import RESULTS, Run

DEVICE_RESULTS = RESULTS / "device_suite"
# name, arguments of the full suite, arguments of --quick, cap in s (full); the caps allow
# for a bare machine's empty kernel cache (H100, 2026-11-27: the localize command's kernels
# took > 90 s to compile, build-map's 57 s; bench_gicp's full run, whose 10,000 per-pose maps
# are built one by one on the host (199 s on the 2-core cpu), did not finish within 180 s on an
# H200, hence 1,000 maps shared in turn and fewer rounds here)
SUITE = [
    ("bench_localize", ["--n", "100000", "1000000", "--m", "256", "1024", "--no-f16",
                        "--repeats", "3"], ["--quick"], 120),
    ("bench_commands", ["--commands", "localize", "--worlds", "office", "--duration", "5",
                        "--threads", str(os.cpu_count())],
     ["--quick", "--commands", "localize", "--particles", "20000"], 150),
    ("bench_slam", ["--particles", "10000", "100000", "--keyframes", "10"], ["--quick"], 90),
    ("bench_gicp", ["--skip-pairwise", "--maps", "1000", "--batch-repeats", "2"],
     ["--quick"], 180),
    ("bench_odometry", ["--quick"], ["--quick"], 80),
    ("bench_tsdf_fusion", [], ["--quick"], 120),
]


def run_bench(name: str, args: list[str], backend: str, cap_s: float) -> dict:
    """One bench; its JSON lands in DEVICE_RESULTS (moved there if the bench wrote to
    bench/results itself, and the cpu figures it replaced are put back)."""
    own = RESULTS / f"{name}.json"
    backup = own.with_suffix(".json.device_suite_backup")
    if own.exists():
        shutil.copy2(own, backup)
    env = {**os.environ, "MCL3D_BENCH_RESULTS": str(DEVICE_RESULTS), "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, str(Path(__file__).parent / f"{name}.py"), *args,
           "--backend", backend]
    print(f"[device_suite] {' '.join(cmd[1:])} (cap {cap_s:.0f} s)", flush=True)
    start = time.time()
    log = DEVICE_RESULTS / f"{name}.log"
    try:
        with open(log, "w") as out:
            rc = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT, timeout=cap_s,
                                env=env).returncode
    except subprocess.TimeoutExpired:
        rc = None
    seconds = time.time() - start
    target = DEVICE_RESULTS / f"{name}.json"
    if own.exists() and own.stat().st_mtime >= start and not _fresh(target, start):
        shutil.move(own, target)
    if backup.exists():
        if not own.exists():
            shutil.move(backup, own)
        else:
            backup.unlink()
    status = "ok" if rc == 0 and _fresh(target, start) else (
        f"stopped at its {cap_s:.0f} s cap" if rc is None else
        f"exit {rc}" if rc else "no JSON written")
    if status != "ok":
        tail = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
        status += f": {tail[-1][:200]}" if tail else ""
    print(f"[device_suite] {name}: {status} ({seconds:.0f} s)", flush=True)
    return {"bench": name, "status": status, "seconds": round(seconds, 1),
            "arguments": " ".join(args)}


def _fresh(path: Path, since: float) -> bool:
    return path.exists() and path.stat().st_mtime >= since


def targets(benches: dict) -> list[dict]:
    """The papers' targets against what the suite measured (None: not measured)."""
    update_ms = next((c["update_ms"] for c in (benches.get("bench_localize", {})
                                               .get("figures", {}).get("cases") or [])
                      if c["N"] == 100_000 and c["M"] == 1024), None)
    raw = benches.get("bench_commands", {}).get("figures", {}).get("raw") or {}
    slam = next((r for r in benches.get("bench_slam", {}).get("figures", {}).get("runs", [])
                 if r.get("particles") == 100_000 and "error" not in r), {})
    rows = [("MCL update, 100,000 particles × 1,024 points (bench_localize)", update_ms, 5.0,
             "ms per update"),
            (f"SLAM frame, whole step, 100,000 particles, {slam.get('keyframes', 10)} "
             "keyframes (bench_slam)",
             statistics.median(f["wall_ms"] for f in slam["frames"]) if slam else None, 50.0,
             "ms per frame")]
    rows = [(*row, "") for row in rows]
    for key, label in (("localize-global", "global"), ("localize-gt", "tracking")):
        v = next((v for k, v in raw.items() if k.endswith(key)), {})
        median = v.get("ms_update_p50")  # the mean holds the rare convergence checks
        rows.append((f"localize command, {label} (bench_commands)", v.get("ms_update_mean"),
                     100.0, "ms per update", "" if median is None else
                     f" (median {median:.1f})"))
    return [{"what": what, "measured": "not measured" if ms is None
             else f"{ms:.1f} {unit}{extra}", "target": f"≤ {target:g} {unit}",
             "pass": "" if ms is None else ("pass" if ms <= target else "FAIL")}
            for what, ms, target, unit, extra in rows]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="cuda", choices=("cuda", "cpu", "vulkan"))
    ap.add_argument("--quick", action="store_true", help="every bench with --quick")
    ap.add_argument("--budget-s", type=float, help="for all benches (default 450, quick 1200)")
    ap.add_argument("--only", nargs="+", help="a subset of the suite")
    args = ap.parse_args()
    args.budget_s = args.budget_s or (1200.0 if args.quick else 450.0)
    run = Run("device_suite" if args.backend == "cuda" else f"device_suite_{args.backend}")
    DEVICE_RESULTS.mkdir(parents=True, exist_ok=True)
    deadline = time.time() + args.budget_s
    statuses = []
    for name, full, quick, cap in SUITE:
        if args.only and name not in args.only:
            continue
        left = deadline - time.time()
        if left < 20:
            statuses.append({"bench": name, "status": "skipped: the suite's time budget is "
                             "spent", "seconds": 0, "arguments": ""})
            continue
        statuses.append(run_bench(name, quick if args.quick else full, args.backend,
                                  min(cap * (3 if args.quick else 1), left)))
    benches = {}
    for s in statuses:
        path = DEVICE_RESULTS / f"{s['bench']}.json"
        if s["status"] == "ok":
            benches[s["bench"]] = json.loads(path.read_text())
    device = os.environ.get("MCL3D_DEVICE_NAME") or next(
        (b["figures"].get("device") for b in benches.values()
         if isinstance(b.get("figures", {}).get("device"), str)), args.backend)
    out = RESULTS / f"{run.name}.json"
    path = run.write({"tables": {f"The papers' targets on {device}": targets(benches),
                                 "Benches of the suite": statuses},
                      "notes": [f"backend {args.backend}; "
                                f"{'--quick sizes' if args.quick else 'full sizes'}; "
                                "each bench's own tables follow."],
                      "device": device, "backend": args.backend, "benches": benches}, out)
    print(f"[device_suite] wrote {path}")
    for row in targets(benches):
        print(f"  {row['what']}: {row['measured']} (target {row['target']}) {row['pass']}")


if __name__ == "__main__":
    main()
