"""Lists Vulkan physical devices through the loader (ctypes), without starting Taichi.

`auto` must prefer a hardware Vulkan device over Mesa's software rasterizer (lavapipe),
which is slower than Taichi's own cpu backend; Taichi itself does not tell them apart.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from dataclasses import dataclass

_VK_STRUCTURE_TYPE_APPLICATION_INFO = 0
_VK_STRUCTURE_TYPE_INSTANCE_CREATE_INFO = 1
_VK_API_VERSION_1_0 = 1 << 22
_DEVICE_TYPES = {0: "other", 1: "integrated-gpu", 2: "discrete-gpu", 3: "virtual-gpu", 4: "cpu"}


class _AppInfo(ctypes.Structure):
    _fields_ = [
        ("sType", ctypes.c_int),
        ("pNext", ctypes.c_void_p),
        ("pApplicationName", ctypes.c_char_p),
        ("applicationVersion", ctypes.c_uint32),
        ("pEngineName", ctypes.c_char_p),
        ("engineVersion", ctypes.c_uint32),
        ("apiVersion", ctypes.c_uint32),
    ]


class _InstanceInfo(ctypes.Structure):
    _fields_ = [
        ("sType", ctypes.c_int),
        ("pNext", ctypes.c_void_p),
        ("flags", ctypes.c_uint32),
        ("pApplicationInfo", ctypes.POINTER(_AppInfo)),
        ("enabledLayerCount", ctypes.c_uint32),
        ("ppEnabledLayerNames", ctypes.c_void_p),
        ("enabledExtensionCount", ctypes.c_uint32),
        ("ppEnabledExtensionNames", ctypes.c_void_p),
    ]


@dataclass(frozen=True)
class VulkanDevice:
    name: str
    device_type: str

    @property
    def is_hardware(self) -> bool:
        return self.device_type in ("integrated-gpu", "discrete-gpu", "virtual-gpu")


def vulkan_devices() -> list[VulkanDevice]:
    """Physical devices the Vulkan loader reports; empty when there is no loader or driver."""
    lib_name = ctypes.util.find_library("vulkan") or "libvulkan.so.1"
    try:
        vk = ctypes.CDLL(lib_name)
    except OSError:
        return []
    app = _AppInfo(_VK_STRUCTURE_TYPE_APPLICATION_INFO, None, b"mcl3d", 1, b"mcl3d", 1,
                   _VK_API_VERSION_1_0)
    info = _InstanceInfo(_VK_STRUCTURE_TYPE_INSTANCE_CREATE_INFO, None, 0, ctypes.pointer(app),
                         0, None, 0, None)
    instance = ctypes.c_void_p()
    if vk.vkCreateInstance(ctypes.byref(info), None, ctypes.byref(instance)) != 0:
        return []
    try:
        count = ctypes.c_uint32(0)
        vk.vkEnumeratePhysicalDevices(instance, ctypes.byref(count), None)
        handles = (ctypes.c_void_p * count.value)()
        vk.vkEnumeratePhysicalDevices(instance, ctypes.byref(count), handles)
        devices = []
        for handle in handles[: count.value]:
            # VkPhysicalDeviceProperties: 4 uint32, deviceType (uint32), char deviceName[256], ...
            props = ctypes.create_string_buffer(4096)
            vk.vkGetPhysicalDeviceProperties(ctypes.c_void_p(handle), props)
            device_type = int.from_bytes(props.raw[16:20], "little")
            name = props.raw[20:276].split(b"\0", 1)[0].decode(errors="replace")
            devices.append(VulkanDevice(name, _DEVICE_TYPES.get(device_type, "other")))
        return devices
    finally:
        vk.vkDestroyInstance(instance, None)
