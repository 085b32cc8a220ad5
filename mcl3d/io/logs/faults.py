"""Faults inside a recording that a run survives: a message published twice, a stamp that goes
back, NaN or inf in an IMU, odometry or ground-truth message, a scan without a valid point.

Such a message is dropped where the log is read (`FaultFilter`, one per pass over the
messages), counted by fault kind with its first stamps in `LogFaults`, and named once in the
run's summary (CONVENTIONS §6): one fault never ends a run. Stamps are compared as integer
nanoseconds, per message kind. A log damaged part way (`LogTruncation`) is read up to the
damage, and damaged stretches in its middle (`LogDamage`) are skipped, reading on at the next
intact chunk; both are named the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FIRST_STAMPS = 5  # stamps kept per fault kind, to find the messages in the log
KIND_NAMES = {"points": "scan", "imu": "imu", "odom": "odometry", "gt": "ground_truth"}
KIND_WORDS = {"scan": ("scan", "scans"), "imu": ("IMU sample", "IMU samples"),
              "odometry": ("odometry message", "odometry messages"),
              "ground_truth": ("ground-truth pose", "ground-truth poses")}
FAULT_WORDS = {"repeated_stamp": "the same stamp as the previous one",
               "stamp_back": "a stamp before the previous one",
               "not_finite": "NaN or inf values", "empty": "no valid point"}


def format_stamp(stamp_ns: int) -> str:
    """Seconds with all nine decimals of an integer-ns stamp, exactly (no float rounding)."""
    sign, ns = ("-", -stamp_ns) if stamp_ns < 0 else ("", stamp_ns)
    return f"{sign}{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


@dataclass
class FaultTally:
    """How many messages one fault kind dropped, and the stamps of the first ones."""

    count: int = 0
    first_stamps_ns: list[int] = field(default_factory=list)

    def add(self, stamp_ns: int) -> None:
        self.count += 1
        if len(self.first_stamps_ns) < FIRST_STAMPS:
            self.first_stamps_ns.append(int(stamp_ns))


@dataclass(frozen=True)
class LogTruncation:
    """A log damaged part way (a recorder killed mid-chunk, an incomplete copy), read up to the
    damage: where the first damaged record starts, and the scans read before the damage."""

    damaged_at_byte: int
    total_bytes: int
    scans_read: int

    def as_dict(self) -> dict:
        return {"damaged_at_byte": self.damaged_at_byte, "total_bytes": self.total_bytes,
                "scans_read": self.scans_read}

    def warning(self) -> str:
        return (f"the log is truncated or damaged at {self.damaged_at_byte / 1e6:.1f} of its "
                f"{self.total_bytes / 1e6:.1f} MB (an interrupted recording or an incomplete "
                f"copy): read the {self.scans_read} scans up to the damage; the rest of the "
                "recording is lost")


@dataclass(frozen=True)
class DamagedStretch:
    """Bytes in the middle of a log that hold no readable record (garbage, a chunk whose CRC
    fails, a zeroed stretch), skipped up to the next intact chunk; the messages they held per
    topic, from the log's message indexes, or None where those are damaged too."""

    start_byte: int
    end_byte: int
    messages_lost: dict[str, int] | None


@dataclass
class LogDamage:
    """The damaged stretches met so far, by start byte (passes over a log meet the same ones);
    `points_topic` names the scans among the messages lost."""

    total_bytes: int
    points_topic: str | None = None
    stretches: dict[int, DamagedStretch] = field(default_factory=dict)

    def add(self, stretch: DamagedStretch) -> None:
        self.stretches.setdefault(stretch.start_byte, stretch)

    def _lost(self, topic: str | None) -> int | None:
        """Messages lost (on `topic`, or on all topics), None when a stretch cannot tell."""
        total = 0
        for s in self.stretches.values():
            if s.messages_lost is None:
                return None
            total += sum(n for t, n in s.messages_lost.items() if topic in (None, t))
        return total

    def as_dict(self) -> dict:
        ordered = sorted(self.stretches.values(), key=lambda s: s.start_byte)
        return {"stretches": [[s.start_byte, s.end_byte] for s in ordered],
                "bytes_lost": sum(s.end_byte - s.start_byte for s in ordered),
                "total_bytes": self.total_bytes,
                "messages_lost": self._lost(None),
                "scans_lost": self._lost(self.points_topic) if self.points_topic else 0}

    def warning(self) -> str:
        d = self.as_dict()
        n = len(d["stretches"])
        lost = ("an unknown number of scans lost" if d["scans_lost"] is None
                else f"{d['scans_lost']} scan{'s' * (d['scans_lost'] != 1)} lost")
        return (f"the log is damaged in {n} place{'s' * (n != 1)} (from byte "
                f"{d['stretches'][0][0]:,}; {d['bytes_lost'] / 1e6:.2f} of its "
                f"{self.total_bytes / 1e6:.1f} MB): skipped the damage and read on from the "
                f"next intact chunk, {lost}")


@dataclass
class LogFaults:
    """The messages a run dropped, by fault kind ("scan_repeated_stamp", "imu_not_finite",
    ...: message kind, then fault). Passes over the same messages find the same faults, so
    each kind keeps the tally of the pass that read the most."""

    tallies: dict[str, FaultTally] = field(default_factory=dict)
    truncation: LogTruncation | None = None  # the log is damaged part way
    damage: LogDamage | None = None  # damaged stretches skipped in the log's middle

    def found(self) -> bool:
        return bool(self.tallies) or self.truncation is not None or self._damaged()

    def _damaged(self) -> bool:
        return self.damage is not None and bool(self.damage.stretches)

    def offer(self, kind: str, tally: FaultTally) -> None:
        """A pass's tally of `kind`, kept when no earlier pass found more."""
        known = self.tallies.get(kind)
        if known is None or tally.count >= known.count:
            self.tallies[kind] = tally

    def count(self, kind: str) -> int:
        tally = self.tallies.get(kind)
        return 0 if tally is None else tally.count

    def as_dict(self) -> dict[str, dict]:
        """The summary's "faults": kind -> count and first stamps (ns)."""
        found = {kind: {"count": t.count, "first_stamps_ns": list(t.first_stamps_ns)}
                 for kind, t in sorted(self.tallies.items())}
        if self.truncation is not None:
            found["log_truncated"] = self.truncation.as_dict()
        if self._damaged():
            found["log_damaged"] = self.damage.as_dict()
        return found

    def warnings(self) -> list[str]:
        """One line per fault kind, naming its first stamps."""
        lines = [] if self.truncation is None else [self.truncation.warning()]
        if self._damaged():
            lines.append(self.damage.warning())
        for kind, t in sorted(self.tallies.items()):
            message, fault = next((m, kind[len(m) + 1:]) for m in KIND_WORDS
                                  if kind.startswith(m + "_"))
            stamps = ", ".join(format_stamp(s) for s in t.first_stamps_ns)
            more = ", ..." if t.count > len(t.first_stamps_ns) else ""
            words = KIND_WORDS[message][t.count != 1]
            lines.append(f"{t.count} {words} dropped with {FAULT_WORDS[fault]} "
                         f"(at {stamps}{more} s)")
        return lines


def _finite(*arrays) -> bool:
    return all(np.isfinite(a).all() for a in arrays)


class FaultFilter:
    """One pass over a log's messages: `keep(kind, msg)` says whether a message is sound,
    and counts it into the run's `LogFaults` when it is not."""

    def __init__(self, faults: LogFaults) -> None:
        self._faults = faults
        self._last_ns: dict[str, int] = {}
        self._tallies: dict[str, FaultTally] = {}

    def keep(self, kind: str, msg) -> bool:
        fault = self._content_fault(kind, msg) or self._stamp_fault(kind, msg.stamp_ns)
        if fault is None:
            self._last_ns[kind] = msg.stamp_ns
            return True
        name = f"{KIND_NAMES[kind]}_{fault}"
        tally = self._tallies.setdefault(name, FaultTally())
        tally.add(msg.stamp_ns)
        self._faults.offer(name, tally)
        return False

    def _stamp_fault(self, kind: str, stamp_ns: int) -> str | None:
        last = self._last_ns.get(kind)
        if last is None or stamp_ns > last:
            return None
        return "repeated_stamp" if stamp_ns == last else "stamp_back"

    @staticmethod
    def _content_fault(kind: str, msg) -> str | None:
        if kind == "points":
            return "empty" if len(msg) == 0 else None
        if kind == "imu":
            if msg.orientation_xyzw is not None and not _finite(msg.orientation_xyzw):
                msg.orientation_xyzw = None  # an orientation it does not have: none given
            sound = _finite(msg.angular_velocity, msg.linear_acceleration)
        elif kind == "odom":
            sound = _finite(msg.T_frame_child, msg.twist)
        else:
            sound = _finite(msg.T)
        return None if sound else "not_finite"
