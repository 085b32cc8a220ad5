"""Backend runtime: the arch obtained is the one asked for, and cpu and vulkan agree."""

import numpy as np
import pytest

from mcl3d.core import runtime
from mcl3d.core.errors import BackendUnavailable, ConfigError


def test_cpu_backend_is_what_runs(ti_runtime):
    import taichi as ti
    from taichi.lang import impl

    assert ti_runtime.backend in ("cpu", "cuda", "vulkan")
    if ti_runtime.backend == "cpu":
        assert impl.current_cfg().arch in (ti.x64, ti.arm64)


def test_unknown_backend_is_a_config_error():
    with pytest.raises(ConfigError, match="unknown backend"):
        runtime.init("metal")


def test_missing_cuda_raises_instead_of_falling_back(monkeypatch):
    monkeypatch.setattr(runtime, "_start", lambda backend, *a: "x64")
    monkeypatch.setattr(runtime, "_current", None)
    with pytest.raises(BackendUnavailable, match=r"cuda.*not available.*cpu backend"):
        runtime.init("cuda")


def test_auto_skips_software_vulkan(monkeypatch):
    from mcl3d.core import vulkan_probe

    started = []
    monkeypatch.setattr(vulkan_probe, "vulkan_devices",
                        lambda: [vulkan_probe.VulkanDevice("llvmpipe", "cpu")])
    monkeypatch.setattr(runtime, "_current", None)
    monkeypatch.setattr(runtime, "_start",
                        lambda backend, *a: started.append(backend) or
                        ("x64" if backend == "cpu" else "unavailable"))
    info = runtime.init("auto")
    assert started == ["cuda", "cpu"] and info.backend == "cpu"
    monkeypatch.setattr(runtime, "_current", None)


def _small_kernel_result() -> np.ndarray:
    """A reduction and a transcendental map: enough to expose f32 or ordering differences."""
    import taichi as ti

    n = 4096
    values = ti.field(ti.f32, shape=n)
    total = ti.field(ti.f32, shape=())

    @ti.kernel
    def fill_and_sum():
        for i in values:
            x = ti.cast(i, ti.f32) * 0.001
            values[i] = ti.sin(x) * ti.exp(-x) + ti.sqrt(x + 1.0)
        for i in values:
            total[None] += values[i]

    fill_and_sum()
    return np.append(values.to_numpy(), total[None])


def test_cpu_and_vulkan_give_the_same_numbers(vulkan_runtime):
    on_vulkan = _small_kernel_result()
    runtime.init("cpu")
    on_cpu = _small_kernel_result()
    x = np.arange(4096) * 0.001
    reference = np.sin(x) * np.exp(-x) + np.sqrt(x + 1.0)
    np.testing.assert_allclose(on_cpu[:-1], reference, rtol=1e-5)
    np.testing.assert_allclose(on_vulkan[:-1], on_cpu[:-1], rtol=1e-6)
    assert abs(on_vulkan[-1] - on_cpu[-1]) / abs(on_cpu[-1]) < 1e-5


def test_restart_starts_the_same_backend_afresh(ti_runtime):
    """A new runtime, equal to the old one, where new fields work; the registration engine
    kept at module level (fields of the old runtime) is built again, not reused."""
    import taichi as ti

    from mcl3d.registration import align

    engine = align._get_engine(1, 100, 100)
    after = runtime.restart()
    assert after is not ti_runtime and after == ti_runtime and runtime.current() is after
    assert align._get_engine(1, 100, 100) is not engine
    values = ti.field(ti.i32, shape=4)
    values.fill(7)
    assert values.to_numpy().tolist() == [7, 7, 7, 7]


def test_restart_without_a_runtime_starts_none(monkeypatch):
    monkeypatch.setattr(runtime, "_current", None)
    assert runtime.restart() is None and runtime.current() is None
