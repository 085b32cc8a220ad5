"""Shared fixtures: the compute backend (cpu unless --backend says otherwise) and real data."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
SHARED_DATA = TESTS.parents[1] / "shared" / "data"


def pytest_addoption(parser):
    parser.addoption("--backend", default="cpu", choices=["cpu", "cuda", "vulkan"],
                     help="compute backend for Taichi tests (default: cpu)")


@pytest.fixture(scope="module", autouse=True)
def fresh_runtime_per_module():
    """Each test file starts on a fresh Taichi runtime (same backend). Every map adds field
    trees and kernels templated on it, and a runtime kept across a worker's files compiles
    ever more slowly. Runs before the file's own module fixtures, which may hold fields."""
    runtime = sys.modules.get("mcl3d.core.runtime")  # not imported yet: no runtime to restart
    running = runtime.current() if runtime is not None else None
    if running is not None and running.backend != "vulkan":  # lavapipe: see `on_vulkan`
        runtime.restart()


@pytest.fixture(scope="session")
def backend(request) -> str:
    """The backend --backend chose. A module fixture that keeps fields (a map) for its tests
    starts the runtime on it: `ti_runtime` switching backends would free those fields."""
    return request.config.getoption("--backend")


@pytest.fixture
def ti_runtime(backend):
    """The Taichi runtime on the chosen backend (started once, restarted if a test switched it)."""
    from mcl3d.core import runtime

    return runtime.init(backend)


class SharedData:
    """../shared/data: `shared_data / "folder"` is that recording's folder, and the test skips
    with the reason when the folder is absent (a machine may hold only some recordings)."""

    def __init__(self, root: Path):
        self.root = root

    def __truediv__(self, name: str) -> Path:
        path = self.root / name
        if not path.exists():
            pytest.skip(f"real recording {name} not found in {self.root}")
        return path


@pytest.fixture(scope="session")
def shared_data() -> SharedData:
    """../shared/data next to the repository; tests that use it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real LiDAR data not found at {SHARED_DATA} (../shared/data next to the repo)")
    return SharedData(SHARED_DATA)


@pytest.fixture
def vulkan_runtime():
    """The Taichi runtime on Vulkan (Mesa's lavapipe in CI); skips when no driver is installed."""
    from mcl3d.core import runtime
    from mcl3d.core.errors import BackendUnavailable
    from mcl3d.core.vulkan_probe import vulkan_devices

    if not vulkan_devices():
        pytest.skip("no Vulkan driver: install mesa-vulkan-drivers and libvulkan1 (setup.sh does)")
    try:
        return runtime.init("vulkan")
    except BackendUnavailable as exc:
        pytest.skip(str(exc))


VULKAN_PROCESS = """
import pickle, sys
from mcl3d.core import runtime
from mcl3d.core.errors import BackendUnavailable
try:
    runtime.init("vulkan")
except BackendUnavailable as exc:
    print(exc, file=sys.stderr)
    sys.exit(77)
from {module} import {function}
with open(sys.argv[1], "rb") as f:
    args = pickle.load(f)
with open(sys.argv[1], "wb") as f:
    pickle.dump({function}("vulkan", *args), f)
"""


@pytest.fixture
def on_vulkan(tmp_path):
    """`run(function, *args)`: function("vulkan", *args) in a fresh process, its result back
    (a module-level function of a test file; arguments and result pickled). Each Vulkan check
    gets its own lavapipe instance: restarts within one worker let driver state build up (a
    worker crashed there, and pytest-xdist hung on it), and a crash now fails one test. Skips
    when no Vulkan driver is installed."""
    import pickle
    import subprocess
    import sys

    from mcl3d.core.vulkan_probe import vulkan_devices

    if not vulkan_devices():
        pytest.skip("no Vulkan driver: install mesa-vulkan-drivers and libvulkan1 (setup.sh does)")

    def run(function, *args):
        exchange = tmp_path / f"{function.__name__}.pickle"
        exchange.write_bytes(pickle.dumps(args))
        code = VULKAN_PROCESS.format(module=function.__module__, function=function.__name__)
        test_dir = Path(sys.modules[function.__module__].__file__).parent
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), str(test_dir)])}
        proc = subprocess.run([sys.executable, "-c", code, str(exchange)], capture_output=True,
                              text=True, cwd=test_dir, env=env, timeout=600)
        if proc.returncode == 77:
            pytest.skip(proc.stderr.strip())
        if proc.returncode != 0:
            pytest.fail(f"the Vulkan process exited with {proc.returncode}:\n{proc.stderr[-3000:]}")
        return pickle.loads(exchange.read_bytes())

    return run
