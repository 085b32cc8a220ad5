"""What a batch writes at its end: results.csv (one row per run), results.json (the rows,
a summary per job and how the batch ran) and the pictures; and the CLI's summary rows."""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mcl3d.batch import plots
from mcl3d.core.outputs import write_text_atomic

CSV_NAME, JSON_NAME = "results.csv", "results.json"
SUCCESS_PICTURE, ATE_PICTURE = "success_vs_particles.png", "ate_per_log.png"


@dataclass(frozen=True)
class BatchOutputs:
    csv: Path
    json: Path
    success_picture: Path
    ate_picture: Path

    @classmethod
    def in_folder(cls, folder: Path) -> BatchOutputs:
        folder = Path(folder)
        return cls(folder / CSV_NAME, folder / JSON_NAME, folder / SUCCESS_PICTURE,
                   folder / ATE_PICTURE)


def columns(rows: list[dict]) -> list[str]:
    """Every key of every row, in the order they first appear (common columns first)."""
    seen: dict[str, None] = {}
    for row in rows:
        seen.update(dict.fromkeys(row))
    return list(seen)


def _median(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return float(np.median(values)) if values else None


def job_summaries(rows: list[dict]) -> list[dict]:
    """Per job: runs, how many ended ok, the success rate (global localization judged against
    ground truth) and the median ATE."""
    out = []
    for job in dict.fromkeys(r["job"] for r in rows):
        rs = [r for r in rows if r["job"] == job]
        judged = [r["success"] for r in rs if r.get("success") is not None]
        out.append({"job": job, "command": rs[0]["command"], "runs": len(rs),
                    "ok": sum(r["status"] == "ok" for r in rs),
                    "success_rate": sum(judged) / len(judged) if judged else None,
                    "median_ate_m": _median([r.get("ate_m") for r in rs])})
    return out


def write_results(outputs: BatchOutputs, rows: list[dict], about: dict) -> list[Path]:
    """results.csv, results.json and the pictures the rows have data for; returns the
    pictures written."""
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=columns(rows), lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: "" if v is None else v for k, v in row.items()} for row in rows)
    write_text_atomic(outputs.csv, text.getvalue())
    write_text_atomic(outputs.json, json.dumps(
        {**about, "jobs": job_summaries(rows), "runs": rows}, indent=2))
    pictures = []
    if plots.success_vs_particles(outputs.success_picture, rows):
        pictures.append(outputs.success_picture)
    if plots.ate_per_log(outputs.ate_picture, rows):
        pictures.append(outputs.ate_picture)
    return pictures


def job_rows(rows: list[dict]) -> list[tuple[str, ...]]:
    """The CLI's table: job, command, runs ok, success rate, median ATE."""
    def text(value, fmt: str) -> str:
        return "-" if value is None else format(value, fmt)

    return [(j["job"], j["command"], f"{j['ok']}/{j['runs']}", text(j["success_rate"], ".0%"),
             text(j["median_ate_m"], ".3f")) for j in job_summaries(rows)]
