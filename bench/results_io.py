"""One header and one place for every benchmark's JSON, so `run_all.py` can gather them.

Each bench writes `bench/results/<name>.json` through `write_result`: the figures it measured
under `"figures"` plus a header naming the machine, the load average before and after, the
versions of mcl3d and of every baseline it ran, the date, the command line and the commit.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

# MCL3D_BENCH_RESULTS moves every bench's JSON elsewhere (bench/device_suite.sh: a GPU run's
# JSON must not replace the cpu figures)
RESULTS = Path(os.environ.get("MCL3D_BENCH_RESULTS") or Path(__file__).resolve().parent / "results")
CORE_PACKAGES = ("mcl3d", "taichi", "numpy", "open3d")


def machine() -> dict:
    """CPU model, logical cores, memory and Python: what a reader needs to place a figure."""
    cpuinfo = Path("/proc/cpuinfo")
    lines = cpuinfo.read_text().splitlines() if cpuinfo.exists() else []
    model = next((line.split(":", 1)[1].strip() for line in lines
                  if line.startswith("model name")), platform.processor())
    meminfo = Path("/proc/meminfo")
    mem_kib = next((int(line.split()[1]) for line in
                    (meminfo.read_text().splitlines() if meminfo.exists() else [])
                    if line.startswith("MemTotal")), 0)
    return {"cpu": model, "cores": os.cpu_count(), "memory_gib": round(mem_kib / 2**20, 1),
            "platform": platform.platform(), "python": platform.python_version()}


def package_versions(extra: tuple[str, ...] = ()) -> dict:
    """Installed versions of mcl3d's core packages and of the given baselines (None if absent)."""
    found = {}
    for name in (*CORE_PACKAGES, *extra):
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            found[name] = None
    return found


def commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, cwd=Path(__file__).parent, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


class Run:
    """Records the load at the start; `write` adds the load at the end and the header."""

    def __init__(self, name: str, baselines: tuple[str, ...] = ()):
        self.name = name
        self.baselines = baselines
        self.load_before = os.getloadavg()[0]
        self.started = time.time()

    def header(self) -> dict:
        return {"name": self.name, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
                "commit": commit(), "machine": machine(),
                "load_average": {"before": round(self.load_before, 2),
                                 "after": round(os.getloadavg()[0], 2)},
                "wall_s": round(time.time() - self.started, 1),
                "versions": package_versions(self.baselines)}

    def write(self, figures: dict, out: Path | None = None) -> Path:
        path = out or RESULTS / f"{self.name}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({**self.header(), "figures": figures}, indent=2,
                                   default=_plain))
        return path


def _plain(value):
    """numpy scalars and arrays in the figures become JSON numbers and lists."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"not JSON serializable: {type(value).__name__}")
