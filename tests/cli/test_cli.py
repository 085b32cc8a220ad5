"""The CLI frame: version, instant help, backend errors as one line with exit 1."""

import subprocess
import sys

import pytest
from typer.testing import CliRunner

from mcl3d import __version__
from mcl3d.cli import app

runner = CliRunner()


def _mcl3d(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mcl3d", *args], capture_output=True,
                          text=True, timeout=120)


def test_version():
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"mcl3d {__version__}"


def test_help_imports_no_heavy_module():
    """`mcl3d --help` stays instant because taichi, open3d and mcap load inside commands."""
    code = ("import sys; from mcl3d.cli import app\n"
            "try: app(['--help'])\nexcept SystemExit: pass\n"
            "heavy = [m for m in ('taichi', 'open3d', 'mcap', 'rosbags', 'matplotlib', 'scipy')"
            " if m in sys.modules]\n"
            "print('HEAVY', heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert "HEAVY []" in out.stdout, out.stdout[-500:]


def test_missing_backend_is_one_line_and_exit_1():
    if _cuda_present():
        pytest.skip("this machine has a CUDA GPU")
    result = _mcl3d("--backend", "cuda", "backends")
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "cuda" in lines[0]
    assert "cpu backend" in lines[0] and "(--backend)" in lines[0]
    assert "Traceback" not in result.stderr + result.stdout


def _cuda_present() -> bool:
    return subprocess.run(["sh", "-c", "command -v nvidia-smi && nvidia-smi -L"],
                          capture_output=True).returncode == 0


def test_per_command_backend_option_overrides_global():
    result = _mcl3d("--backend", "cuda", "backends", "--backend", "cpu")
    assert result.returncode == 0, result.stderr
    assert "cpu" in result.stdout


def test_unknown_backend_is_a_usage_error():
    result = runner.invoke(app, ["--backend", "metal", "backends"])
    assert result.exit_code == 2
