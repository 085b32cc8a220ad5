"""One Taichi runtime per process, on the backend the user asked for and no other.

Taichi silently falls back to cpu when a backend is missing; we check the arch actually
obtained and raise `BackendUnavailable` instead, so a benchmark never reports cpu numbers
as GPU numbers.
"""

from __future__ import annotations

import contextlib
import gc
import io
import os
import subprocess
from dataclasses import dataclass

import taichi as ti
from taichi._lib import core as ti_core
from taichi.lang import impl

from mcl3d.core.errors import BackendUnavailable, ConfigError
from mcl3d.core.vulkan_probe import vulkan_devices
from mcl3d.kernels import taichi_frontend

BACKENDS = ("auto", "cuda", "vulkan", "cpu")


@dataclass(frozen=True)
class RuntimeInfo:
    backend: str  # "cuda" | "vulkan" | "cpu": what is running, never "auto"
    device: str  # human-readable device name
    requested: str  # what the user asked for


# Taichi's on-disk kernel cache evicts the least recently used kernels above 100 MiB by
# default; mcl3d's kernels (maps of several layouts, every backend) take more, so each
# command recompiled what another had evicted (~2 cpu-s per build-map)
KERNEL_CACHE_BYTES = 1 << 30
_current: RuntimeInfo | None = None
_options: dict = {}  # the keyword options `init` started the running runtime with


def current() -> RuntimeInfo | None:
    """The running runtime, or None before `init`."""
    return _current


def _start(backend: str, offline_cache: bool, debug: bool) -> str:
    """ti.init on exactly `backend`; returns the arch name Taichi actually started."""
    arch = {"cuda": ti.cuda, "vulkan": ti.vulkan, "cpu": ti.cpu}[backend]
    taichi_frontend.install()
    ti.reset()
    quiet = io.StringIO()
    try:
        with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
            ti.init(
                arch=arch,
                default_fp=ti.f32,
                default_ip=ti.i32,
                offline_cache=offline_cache,
                offline_cache_max_size_of_files=KERNEL_CACHE_BYTES,
                debug=debug,
                log_level=ti.ERROR,
                enable_fallback=False,
            )
    except RuntimeError:
        return "unavailable"
    return ti_core.arch_name(impl.current_cfg().arch)


def _cpu_name() -> str:
    with contextlib.suppress(OSError), open("/proc/cpuinfo") as f:
        for line in f:
            if line.startswith("model name"):
                return f"{line.split(':', 1)[1].strip()} ({os.cpu_count()} threads)"
    return f"cpu ({os.cpu_count()} threads)"


def _missing_message(backend: str) -> str:
    if backend == "cuda":
        return ("backend 'cuda' is not available on this machine (no NVIDIA GPU or CUDA driver "
                "found); use the cpu backend, or auto to take the best one present")
    return ("backend 'vulkan' is not available on this machine (no Vulkan driver found); "
            "install one (e.g. `apt-get install mesa-vulkan-drivers libvulkan1`) "
            "or use the cpu backend")


def _started_as(backend: str, arch_name: str) -> bool:
    expected = {"cuda": ("cuda",), "vulkan": ("vulkan",), "cpu": ("x64", "arm64")}[backend]
    return arch_name in expected


def init(backend: str = "auto", *, offline_cache: bool = True, debug: bool = False) -> RuntimeInfo:
    """Start Taichi on `backend` (auto|cuda|vulkan|cpu) and return what was started.

    `auto` prefers cuda, then a hardware Vulkan device (not Mesa's software lavapipe, which
    is slower than the cpu backend), then cpu. Calling again with the same request is a
    no-op; with another request it restarts Taichi (fields allocated before are lost).
    """
    global _current
    if backend not in BACKENDS:
        raise ConfigError(f"unknown backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if _current is not None and _current.requested == backend:
        return _current

    if backend == "auto":
        hardware_vulkan = [d for d in vulkan_devices() if d.is_hardware]
        candidates = ["cuda", *(["vulkan"] if hardware_vulkan else []), "cpu"]
    else:
        candidates = [backend]
    for candidate in candidates:
        arch_name = _start(candidate, offline_cache, debug)
        if _started_as(candidate, arch_name):
            _current = RuntimeInfo(candidate, _device_name(candidate), backend)
            _options.update(offline_cache=offline_cache, debug=debug)
            return _current
    raise BackendUnavailable(_missing_message(backend), setting="backend")


def restart() -> RuntimeInfo | None:
    """Start the running runtime afresh, same request and options; None when none runs.

    Every field and kernel of the old one is gone: objects holding them must not be used
    again. Taichi compiles a kernel more slowly the more field trees a runtime holds, so a
    process that builds many maps one after another (the test suite) restarts between them.
    """
    global _current
    if _current is None:
        return None
    requested, _current = _current.requested, None
    gc.collect()  # Taichi objects dropped since are freed by the runtime that made them
    return init(requested, **_options)


def loop_threads() -> int:
    """Threads the cpu backend splits a parallel loop over (kernels.spread), 1 elsewhere."""
    if _current is None or _current.backend != "cpu":
        return 1
    return max(1, int(impl.current_cfg().cpu_max_num_threads))


def _device_name(backend: str) -> str:
    if backend == "cpu":
        return _cpu_name()
    if backend == "vulkan":
        devices = vulkan_devices()
        hardware = [d for d in devices if d.is_hardware]
        chosen = (hardware or devices)[0] if devices else None
        return chosen.name if chosen else "vulkan device"
    with contextlib.suppress(Exception):
        out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=5)
        if out.returncode == 0 and out.stdout.strip():
            return out.stdout.strip().splitlines()[0]
    return "CUDA device"
