"""A loader for the scripts in bench/, which are not a package: `bench("name")` imports
bench/name.py and forgets it after the test (so a test's monkeypatching does not leak)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"


@pytest.fixture
def bench(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    loaded = {}

    def load(name: str):
        loaded[name] = importlib.import_module(name)
        return loaded[name]

    yield load
    for name in loaded:
        sys.modules.pop(name, None)
