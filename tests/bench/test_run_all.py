"""bench/run_all.py renders docs/results.md from the benches' JSON: tables, notes, failures,
and a study's earlier text when its JSON is absent."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.fixture
def run_all(bench, tmp_path, monkeypatch):
    module = bench("run_all")
    monkeypatch.setattr(module, "RESULTS", tmp_path)
    return module


def write_result(folder: Path, name: str, figures: dict) -> None:
    header = {"name": name, "date": "2026-11-26 12:00 UTC", "command": f"{name}.py --quick",
              "machine": {"cpu": "Test CPU", "cores": 2, "memory_gib": 8.0, "python": "3.11"},
              "load_average": {"before": 0.5, "after": 1.5}, "wall_s": 12.3,
              "versions": {"mcl3d": "0.1.0", "kiss-icp": "1.3.0"}}
    (folder / f"{name}.json").write_text(json.dumps({**header, "figures": figures}))


def test_markdown_table_takes_every_column_and_escapes_pipes(run_all):
    table = run_all.markdown_table([{"a": 1, "b": "x|y"}, {"a": 2.5, "c": None}])
    assert table.splitlines() == ["| a | b | c |", "| --- | --- | --- |",
                                  "| 1 | x\\|y |  |", "| 2.5 |  |  |"]


def test_render_tables_notes_failures_and_earlier_study_text(run_all, tmp_path):
    write_result(tmp_path, "bench_localize", {
        "tables": {"MCL update": [{"N": "10,000", "update ms": 12.5}]},
        "notes": ["particles spread around the truth"]})
    statuses = {"bench_gicp": {"status": "failed", "reason": "exit 1: boom"}}
    page = run_all.render(statuses)
    assert "| N | update ms |\n| --- | --- |\n| 10,000 | 12.5 |" in page
    assert "- particles spread around the truth" in page
    assert "kiss-icp 1.3.0" in page and "Test CPU, 2 logical cores" in page
    assert "*No results: `bench/bench_gicp.py` failed: exit 1: boom.*" in page
    measured, _ = run_all.LEGACY["soak"]
    assert f"*Measured on {measured} by an earlier run of `bench/soak.py`" in page
    assert "No GPU measured" in page


def test_device_suite_renders_the_cuda_section(run_all, tmp_path):
    bench = {"name": "bench_localize", "figures": {"tables": {"MCL update": [{"N": 1}]}}}
    write_result(tmp_path, "device_suite", {
        "tables": {"The papers' targets": [{"what": "update", "measured": "4.0 ms",
                                            "target": "≤ 5 ms", "pass": "pass"}]},
        "device": "NVIDIA H100", "benches": {"bench_localize": bench}})
    write_result(tmp_path, "device_suite_cpu", {"tables": {}, "device": "cpu"})
    page = run_all.render({})
    cuda = page[page.index("## cuda (device suite)"):]
    assert "NVIDIA H100" in cuda and "| update | 4.0 ms | ≤ 5 ms | pass |" in cuda
    assert "### cuda: Localization update" in cuda and "| N |\n| --- |\n| 1 |" in cuda
    assert "device_suite_cpu" not in page
