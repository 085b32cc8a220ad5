"""Writes ouster_sdk_reference.json: what the Ouster SDK decodes from the real OS1-128 pcap in
../shared/data/ouster_os1_128_lb_n3 (BSD-3-Clause, Ouster), for tests/io/test_ouster_pcap.py.

The SDK cannot be a test dependency (ouster-sdk 1.0.1 pins rosbags==0.9.23, mcl3d needs
rosbags>=0.10), so its decode is recorded once: per frame its id, first column time, number
of returns, and the sensor-frame xyz of 300 returns drawn with seed 0. To regenerate, in an
environment where `import ouster.sdk` works (e.g. `pip install --no-deps --target DIR
ouster-sdk==1.0.1`, then PYTHONPATH=DIR):

    python tests/support/make_ouster_sdk_reference.py ../shared/data/ouster_os1_128_lb_n3
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

STEM = "OS-1-128_v2.3.0_1024x10"
SAMPLES = 300


def sdk_frames(folder: Path):
    """(frame id, first column time ns, range image, xyz image) per frame, by the SDK."""
    from ouster.sdk import core, open_source

    source = open_source(str(folder / f"{STEM}_lb_n3.pcap"), meta=[str(folder / f"{STEM}.json")])
    lut = core.XYZLut(source.sensor_info[0], use_extrinsics=False)
    for frames in source:
        scan = frames[0]
        rng = scan.field("RANGE")
        yield int(scan.frame_id), int(scan.timestamp.min()), rng, lut(rng)


def main(folder: Path) -> None:
    rng = np.random.default_rng(0)
    out = {"sdk": "ouster-sdk 1.0.1, XYZLut(info, use_extrinsics=False)", "frames": []}
    for frame_id, first_ns, ranges, xyz in sdk_frames(folder):
        rows, cols = np.nonzero(ranges > 0)
        pick = np.sort(rng.choice(len(rows), SAMPLES, replace=False))
        out["frames"].append({
            "frame_id": frame_id, "first_column_ns": first_ns, "returns": len(rows),
            "row": rows[pick].tolist(), "column": cols[pick].tolist(),
            "xyz": [[round(float(v), 7) for v in p] for p in xyz[rows[pick], cols[pick]]]})
    target = Path(__file__).with_name("ouster_sdk_reference.json")
    target.write_text(json.dumps(out, separators=(",", ":")) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
