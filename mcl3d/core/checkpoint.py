"""Checkpoints of a long run: the outputs so far, rewritten every so often, so a crash or a
kill -9 keeps the poses done (no resume needed). The run's final outputs replace them. Each
file is written atomically, one after the other: the summary is written last, so a kill between
them leaves it one checkpoint behind the trajectory."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path

from mcl3d.core.outputs import atomic_open

CHECKPOINT_INTERVAL_S = 30.0  # wall time between checkpoints
CHECKPOINT_ENV = "MCL3D_CHECKPOINT_S"  # overrides the interval (seconds), e.g. for tests


def checkpoint_interval_s() -> float:
    """The interval: $MCL3D_CHECKPOINT_S when set, else `CHECKPOINT_INTERVAL_S`."""
    value = os.environ.get(CHECKPOINT_ENV)
    return CHECKPOINT_INTERVAL_S if not value else float(value)


class Checkpointer:
    """Calls `write` from `tick` once at least the interval has passed since the run started
    or since the last checkpoint; a tick in between costs one clock read."""

    def __init__(self, write: Callable[[], None], interval_s: float | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.write, self.clock = write, clock
        self.interval_s = checkpoint_interval_s() if interval_s is None else interval_s
        self.last_s = clock()
        self.count = 0

    def tick(self) -> None:
        if self.clock() - self.last_s >= self.interval_s:
            self.write()
            self.count += 1
            self.last_s = self.clock()


def write_checkpoint_summary(path: Path, fields: dict) -> None:
    """The summary so far, marked `"checkpoint": true` (the final summary has no such key)."""
    with atomic_open(path, "w") as f:
        json.dump({"checkpoint": True, **fields}, f, indent=2)
