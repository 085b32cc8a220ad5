"""Log I/O throughput and memory: write and read an OS1-64-sized ROS 2 MCAP with mcl3d.

`mcl3d info` must stay fast whatever the log size (it decodes only a few scans).
Baseline, measured in the same run: iterating the same file's raw MCAP records with the
`mcap` library (no CDR decoding, no point extraction). Memory: peak RSS growth while reading
the whole log, which must stay far below the file size (streaming). Prints a table and
writes bench/results/bench_logs.json through results_io.

    python bench/bench_logs.py [--quick] --scans 100
"""

from __future__ import annotations

import argparse
import platform
import resource
import tempfile
import time
from pathlib import Path

import numpy as np
from results_io import Run


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def make_scan(rng, stamp_ns: int, height: int, width: int):
    from mcl3d.io.logs.messages import PointCloud

    n = height * width
    az = np.tile(np.linspace(0, 2 * np.pi, width, endpoint=False), height)
    el = np.repeat(np.linspace(-0.39, 0.39, height), width)
    r = rng.uniform(1, 60, n)
    points = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                       r * np.sin(el)], axis=1).astype(np.float32)
    return PointCloud(stamp_ns, "lidar", points, np.tile(np.linspace(0, 0.1, width,
                                                                     dtype=np.float32), height),
                      {"intensity": rng.uniform(0, 1000, n).astype(np.float32),
                       "ring": np.repeat(np.arange(height, dtype=np.uint16), width)},
                      height=height, width=width)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=None, help="default 100, --quick 20")
    parser.add_argument("--quick", action="store_true", help="20 scans")
    parser.add_argument("--backend", default="cpu", help="accepted for run_all; log I/O is host")
    parser.add_argument("--height", type=int, default=64)
    parser.add_argument("--width", type=int, default=2048)
    parser.add_argument("--out", type=Path, help="JSON (default bench/results/bench_logs.json)")
    args = parser.parse_args()
    args.scans = args.scans or (20 if args.quick else 100)
    bench_run = Run("bench_logs", baselines=("mcap",))

    from mcap.reader import make_reader

    from mcl3d.io.logs.messages import Imu
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.logs.writer import LogWriter

    rng = np.random.default_rng(0)
    scans = [make_scan(rng, 0, args.height, args.width) for _ in range(4)]  # reused payloads
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.mcap"
        start = time.perf_counter()
        with LogWriter(path) as w:
            for k in range(args.scans):
                stamp = 1_700_000_000_000_000_000 + k * 100_000_000
                cloud = scans[k % len(scans)]
                cloud.stamp_ns = stamp
                w.write_points("/lidar/points", cloud)
                for j in range(10):
                    w.write_imu("/imu/data", Imu(stamp + j * 10_000_000, "imu", np.zeros(3),
                                                 np.array([0, 0, 9.81])))
        write_s = time.perf_counter() - start
        size_mb = path.stat().st_size / 1e6

        start = time.perf_counter()
        with open(path, "rb") as f:
            raw_bytes = sum(len(m.data) for _s, _c, m in make_reader(f).iter_messages())
        raw_s = time.perf_counter() - start

        rss_before, rss_peak, points = rss_mb(), 0.0, 0
        start = time.perf_counter()
        with LogReader(path) as r:
            for _kind, msg in r.messages(("points", "imu")):
                if hasattr(msg, "points"):
                    points += len(msg.points)
                    rss_peak = max(rss_peak, rss_mb())
        read_s = time.perf_counter() - start

        from mcl3d.io.logs.info import log_info

        start = time.perf_counter()
        log_info(path)
        info_s = time.perf_counter() - start

    rows = [
        ("write (mcl3d LogWriter)", write_s, args.scans / write_s, size_mb / write_s),
        ("read raw records (mcap, baseline)", raw_s, args.scans / raw_s, raw_bytes / 1e6 / raw_s),
        ("read + decode scans (mcl3d LogReader)", read_s, args.scans / read_s,
         size_mb / read_s),
    ]
    print(f"log: {args.scans} scans of {args.height}x{args.width} + {10 * args.scans} IMU, "
          f"{size_mb:.0f} MB on disk; machine: {platform.processor() or platform.machine()}")
    print(f"{'step':40s} {'seconds':>8s} {'scans/s':>9s} {'MB/s':>8s}")
    for name, seconds, rate, mbps in rows:
        print(f"{name:40s} {seconds:8.2f} {rate:9.1f} {mbps:8.1f}")
    print(f"{'mcl3d info (summary + 3 decoded scans)':40s} {info_s:8.2f}")
    growth = rss_peak - rss_before
    print(f"decode cost vs raw baseline: {read_s / raw_s:.2f}x; peak RSS growth while reading: "
          f"{growth:.0f} MB for a {size_mb:.0f} MB log")
    table = [{"step": name, "seconds": round(seconds, 3), "scans/s": round(rate, 1),
              "MB/s": round(mbps, 1)} for name, seconds, rate, mbps in rows]
    table.append({"step": "mcl3d info (summary + 3 decoded scans)", "seconds": round(info_s, 3),
                  "scans/s": "", "MB/s": ""})
    path = bench_run.write({
        "tables": {f"{args.scans} scans of {args.height}×{args.width} points + "
                   f"{10 * args.scans} IMU messages, {size_mb:.0f} MB": table},
        "notes": [f"Reading and decoding takes {read_s / raw_s:.2f}× the raw mcap iteration "
                  f"(the baseline); peak RSS grows {growth:.0f} MB while reading the whole "
                  f"{size_mb:.0f} MB log (streaming)."],
        "scans": args.scans, "height": args.height, "width": args.width, "size_mb": size_mb,
        "points_read": points, "write_s": write_s, "raw_read_s": raw_s, "read_s": read_s,
        "read_vs_raw_ratio": read_s / raw_s, "info_s": info_s, "rss_growth_mb": growth},
        args.out)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
