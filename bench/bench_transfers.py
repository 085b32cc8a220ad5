"""Bytes crossing host <-> device per `localize` update, vs the particle count N.

A GPU is capped when every update copies per-particle arrays to the host and back: the
copies grow with N and the host work on them serializes the device. This bench counts, for
each update of a `Localizer` on a simulated office log, every transfer Taichi makes:

- `to_numpy` (device -> host) and `from_numpy` (host -> device) of fields and ndarrays;
- numpy arrays passed to kernels (Taichi copies them to the device and back on cuda, so
  their bytes count both ways);
- element reads and writes of fields from Python (`field[i]`) and kernel return values.

It runs global search (uniform over the free space: coarse scans, then the accurate model
with place evidence and mode-preserving resampling, `coarse_scans` shortened to 2) and
tracking (a cloud around the true pose, converged) at N = 10k, 100k, 1M particles x 256
points, and reports the largest bytes of an update in each phase, bytes per particle, and the
host's share of the update time: the update's wall time minus the time inside Taichi kernel
launches (on the cpu backend a launch returns when the kernel is done), over the wall time.
Resampling is forced every update so that every stage counts.

    python bench/bench_transfers.py [--quick] [--backend cpu] [--state "label"]
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from bench_localize import ensure_data, scans_with_motion
from results_io import Run

GLOBAL_UPDATES, GLOBAL_COARSE_SCANS = 7, 2
TRACKING_UPDATES = 5
WARM_UPDATES = 2  # of a phase, not timed: they compile kernels for both particle buffers


@dataclass
class Traffic:
    """Bytes and calls of one update, by kind of transfer."""

    h2d: int = 0
    d2h: int = 0
    calls: dict = field(default_factory=dict)
    kernel_s: float = 0.0

    def add(self, kind: str, h2d: int, d2h: int) -> None:
        self.h2d += int(h2d)
        self.d2h += int(d2h)
        self.calls[kind] = self.calls.get(kind, 0) + 1


class TransferCounter:
    """Wraps Taichi's transfer entry points and kernel launches to count bytes and time."""

    def __init__(self) -> None:
        self.traffic = Traffic()
        self._depth = 0  # inside a to_numpy/from_numpy (its own kernel is the copy)

    def install(self) -> None:
        fld = importlib.import_module("taichi.lang.field")
        mat = importlib.import_module("taichi.lang.matrix")
        nd = importlib.import_module("taichi.lang._ndarray")
        ki = importlib.import_module("taichi.lang.kernel_impl")
        for cls in (fld.ScalarField, mat.MatrixField, nd.ScalarNdarray, nd.Ndarray):
            if "to_numpy" in vars(cls):
                cls.to_numpy = self._wrap_copy(cls.to_numpy, "to_numpy", down=True)
            if "from_numpy" in vars(cls):
                cls.from_numpy = self._wrap_copy(cls.from_numpy, "from_numpy", down=False)
        for cls in (fld.ScalarField, mat.MatrixField):
            cls.__getitem__ = self._wrap_item(cls.__getitem__, down=True)
            cls.__setitem__ = self._wrap_item(cls.__setitem__, down=False)
        ki.Kernel.__call__ = self._wrap_kernel(ki.Kernel.__call__)

    def take(self) -> Traffic:
        out, self.traffic = self.traffic, Traffic()
        return out

    def _wrap_copy(self, fn, kind: str, down: bool):
        counter = self

        def wrapped(obj, *args, **kwargs):
            counter._depth += 1
            try:
                out = fn(obj, *args, **kwargs)
            finally:
                counter._depth -= 1
            if counter._depth == 0:
                arr = out if down else args[0]
                nbytes = np.asarray(arr).nbytes
                counter.traffic.add(kind, 0 if down else nbytes, nbytes if down else 0)
            return out
        return wrapped

    def _wrap_item(self, fn, down: bool):
        counter = self

        def wrapped(obj, *args):
            out = fn(obj, *args)
            if counter._depth == 0:
                n = int(np.prod(getattr(obj, "n", 1) or 1) * np.prod(getattr(obj, "m", 1) or 1))
                counter.traffic.add("element", 0 if down else 4 * n, 4 * n if down else 0)
            return out
        return wrapped

    def _wrap_kernel(self, fn):
        counter = self

        def wrapped(kernel, *args, **kwargs):
            if counter._depth:
                return fn(kernel, *args, **kwargs)
            t0 = time.perf_counter()
            out = fn(kernel, *args, **kwargs)
            counter.traffic.kernel_s += time.perf_counter() - t0
            arrays = [a for a in (*args, *kwargs.values()) if isinstance(a, np.ndarray)]
            nbytes = sum(a.nbytes for a in arrays)
            if nbytes:
                counter.traffic.add("kernel_numpy_arg", nbytes, nbytes)
            if out is not None:
                counter.traffic.add("kernel_return", 0, np.asarray(out).nbytes or 4)
            return out
        return wrapped


def run_case(tsdf, scans, n: int, mode: str, counter: TransferCounter) -> dict:
    from mcl3d.localization.localization_config import LocalizerConfig
    from mcl3d.localization.localizer import Localizer

    cfg = LocalizerConfig.model_validate({
        "particles": n, "seed": 1, "sensor": {"points": 256,
                                              "coarse_scans": GLOBAL_COARSE_SCANS},
        "resample": {"ess_threshold": 1.0}, "recovery": {"enabled": False}})
    loc = Localizer(tsdf, cfg)
    if mode == "global":
        loc.init_global()
    else:
        loc.init_pose(scans[0][1], [0.3, 0.3, 0.05, 0.02, 0.02, 0.1])
        loc.ever_converged = True
    rows, T_prev = [], None
    for k, (points, T, stamp_s) in enumerate(scans):
        motion = None if T_prev is None else np.linalg.inv(T_prev) @ T
        T_prev = T
        import taichi as ti

        ti.sync()
        counter.take()
        t0, c0 = time.perf_counter(), time.process_time()
        r = loc.step(points, motion, stamp_s)
        ti.sync()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        t = counter.take()
        phase = ("coarse" if k < GLOBAL_COARSE_SCANS else "search") if mode == "global" \
            else "tracking"
        rows.append({"phase": phase, "h2d": t.h2d, "d2h": t.d2h, "calls": t.calls,
                     "wall_ms": 1e3 * wall, "cpu_ms": 1e3 * cpu,
                     "host_ms": 1e3 * (wall - t.kernel_s), "state": r.state.value})
    return {"N": n, "mode": mode, "updates": rows}


def summarize(case: dict) -> list[dict]:
    """One row per phase: the largest update's bytes, median times (the phase's first
    `WARM_UPDATES` excluded where it has more: they compile kernels for this set's fields)."""
    out = []
    for phase in dict.fromkeys(r["phase"] for r in case["updates"]):
        rows = [r for r in case["updates"] if r["phase"] == phase]
        timed = rows[WARM_UPDATES:] or rows[-1:]
        total = max(r["h2d"] + r["d2h"] for r in rows)
        wall = statistics.median(r["wall_ms"] for r in timed)
        host = statistics.median(r["host_ms"] for r in timed)
        out.append({"N": f"{case['N']:,}", "phase": phase,
                    "bytes/update": f"{total:,}",
                    "bytes/particle": round(total / case["N"], 2),
                    "host->device": f"{max(r['h2d'] for r in rows):,}",
                    "device->host": f"{max(r['d2h'] for r in rows):,}",
                    "update ms": round(wall, 1), "host ms": round(host, 1),
                    "host share": f"{100 * host / wall:.0f} %"})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--quick", action="store_true", help="N in 10k, 100k; fewer updates")
    ap.add_argument("--n", type=int, nargs="+", help="particle counts (default 10k 100k 1M)")
    ap.add_argument("--cache-dir", type=Path, default=Path("/tmp/mcl3d-bench"))
    ap.add_argument("--state", default="", help="what code state this measures (a label)")
    ap.add_argument("--out", type=Path, help="JSON path (default bench/results/...)")
    args = ap.parse_args()
    run = Run("bench_transfers")

    from mcl3d.core import runtime
    from mcl3d.maps.map_file import load_map

    log, map_path = ensure_data(args.cache_dir, None, None)
    info = runtime.init(args.backend)
    counter = TransferCounter()
    counter.install()
    tsdf = load_map(map_path)
    ns = args.n or ([10_000, 100_000] if args.quick else [10_000, 100_000, 1_000_000])
    n_global = GLOBAL_COARSE_SCANS + (3 if args.quick else GLOBAL_UPDATES - GLOBAL_COARSE_SCANS)
    scans = scans_with_motion(log, max(n_global, TRACKING_UPDATES))
    cases, rows = [], []
    for mode, count in (("global", n_global), ("tracking", TRACKING_UPDATES)):
        for n in ns:
            case = run_case(tsdf, scans[:count], n, mode, counter)
            cases.append(case)
            rows += summarize(case)
            print(rows[-1], flush=True)
    caption = (f"Host <-> device bytes per localize update ({args.state or 'this commit'}; "
               f"{info.backend}, 256 points, largest update of each phase)")
    figures = {"backend": info.backend, "device": info.device, "state": args.state,
               "log": str(log), "map": str(map_path), "cases": cases,
               "tables": {caption: rows},
               "notes": ["bytes: to_numpy/from_numpy, numpy kernel arguments (both ways), "
                         "field element access and kernel returns, counted by wrapping "
                         "Taichi's entry points (bench/bench_transfers.py)",
                         "host share: update wall time outside Taichi kernel launches "
                         f"(cpu backend: launches are synchronous); seed 1, "
                         f"{GLOBAL_COARSE_SCANS} coarse scans"]}
    print(run.write(figures, args.out))
    for r in rows:
        print(r)


if __name__ == "__main__":
    main()
