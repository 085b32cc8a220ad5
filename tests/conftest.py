"""Shared fixtures: the compute backend (cpu unless --backend says otherwise) and real data."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def pytest_addoption(parser):
    parser.addoption("--backend", default="cpu", choices=["cpu", "cuda", "vulkan"],
                     help="compute backend for Taichi tests (default: cpu)")


@pytest.fixture
def ti_runtime(request):
    """The Taichi runtime on the chosen backend (started once, restarted if a test switched it)."""
    from mcl3d import runtime

    return runtime.init(request.config.getoption("--backend"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data next to the repository; tests that use it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real LiDAR data not found at {SHARED_DATA} (../shared/data next to the repo)")
    return SHARED_DATA


@pytest.fixture
def vulkan_runtime():
    """The Taichi runtime on Vulkan (Mesa's lavapipe in CI); skips when no driver is installed."""
    from mcl3d import runtime
    from mcl3d.errors import BackendUnavailable
    from mcl3d.vulkan_probe import vulkan_devices

    if not vulkan_devices():
        pytest.skip("no Vulkan driver: install mesa-vulkan-drivers and libvulkan1 (setup.sh does)")
    try:
        return runtime.init("vulkan")
    except BackendUnavailable as exc:
        pytest.skip(str(exc))
