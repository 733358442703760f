"""Starting the engine for a command, and saying which device the kernels run on.

`--arch gpu` takes whatever GPU backend Taichi finds. On a machine without CUDA
that may be Vulkan on Mesa's llvmpipe/lavapipe: a CPU pretending to be a GPU,
many times slower than Taichi's own CPU backend. So a GPU run names its device,
and warns when that device is a software one.
"""

import ctypes
import ctypes.util
import os
import re
import sys

import fem
from fem.errors import FemError
from fem.runtime import NoGpuError

# VkPhysicalDeviceType: VK_PHYSICAL_DEVICE_TYPE_INTEGRATED_GPU = 1, DISCRETE_GPU = 2, CPU = 4.
VULKAN_CPU_TYPE = 4
# Taichi's Vulkan backend prefers a discrete GPU, then an integrated one (get_device_score).
VULKAN_PREFERENCE = {2: 2, 1: 1}
SOFTWARE_NAMES = re.compile(r"llvmpipe|lavapipe|softpipe|swiftshader", re.IGNORECASE)


def start(args) -> dict:
    """fem.init as the command line asks (--arch, --precision, --debug); unless the
    backend is the CPU by request, one line on stderr says which device was picked."""
    try:
        backend = fem.init(args.arch, args.precision, debug=args.debug,
                           profile=getattr(args, "profile", False))
    except NoGpuError:
        raise FemError("--arch gpu: no GPU backend found on this machine (use --arch cpu or auto)") from None
    found = describe(backend)
    if args.arch != "cpu":
        print(report(args.arch, found), file=sys.stderr)
    return found


def describe(backend: str) -> dict:
    """{"backend", "name", "software"}: the Taichi backend's device, its name (None when it
    cannot be found out) and whether it is a CPU emulating a GPU."""
    name, software = None, False
    if backend in ("x64", "arm64"):
        name = cpu_name()
    elif backend == "cuda":
        name = cuda_device_name()
    elif backend == "vulkan":
        devices = vulkan_devices()
        if devices:
            name, kind = pick_vulkan_device(devices, os.environ.get("TI_VISIBLE_DEVICE"))
            software = kind == VULKAN_CPU_TYPE or bool(SOFTWARE_NAMES.search(name))
    return {"backend": backend, "name": name, "software": software}


def report(arch: str, found: dict) -> str:
    """The line a user reads about the device of `--arch arch`."""
    backend = {"x64": "the CPU", "arm64": "the CPU", "cuda": "CUDA", "vulkan": "Vulkan",
               "opengl": "OpenGL", "metal": "Metal"}.get(found["backend"], found["backend"])
    device = f" ({found['name']})" if found["name"] else ""
    if found["software"]:
        return (f"warning: --arch {arch}: running on {backend}{device}, a software device "
                f"(the CPU emulating a GPU), usually many times slower than --arch cpu; "
                f"use --arch cpu, or install the GPU's own Vulkan driver")
    if arch == "auto" and found["backend"] in ("x64", "arm64"):
        return f"--arch auto: no CUDA GPU found; running on the CPU{device}"
    return f"--arch {arch}: running on {backend}{device}"


def pick_vulkan_device(devices, visible=None):
    """The (name, type) Taichi's Vulkan backend uses among devices [(name, type)]:
    $TI_VISIBLE_DEVICE's index when valid, else the first discrete GPU, else the first
    integrated one, else the first device."""
    if visible is not None and visible.isdigit() and int(visible) < len(devices):
        return devices[int(visible)]
    return max(devices, key=lambda d: VULKAN_PREFERENCE.get(d[1], 0))


def cpu_name() -> str | None:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def cuda_device_name() -> str | None:
    """The name of CUDA device 0 from the driver library, or None."""
    try:
        cuda = ctypes.CDLL(ctypes.util.find_library("cuda") or "libcuda.so.1")
        device, name = ctypes.c_int(), ctypes.create_string_buffer(256)
        if cuda.cuInit(0) or cuda.cuDeviceGet(ctypes.byref(device), 0) or \
                cuda.cuDeviceGetName(name, 256, device):
            return None
        return name.value.decode(errors="replace")
    except (OSError, AttributeError):
        return None


class _ApplicationInfo(ctypes.Structure):
    _fields_ = [("sType", ctypes.c_int), ("pNext", ctypes.c_void_p),
                ("pApplicationName", ctypes.c_char_p), ("applicationVersion", ctypes.c_uint32),
                ("pEngineName", ctypes.c_char_p), ("engineVersion", ctypes.c_uint32),
                ("apiVersion", ctypes.c_uint32)]


class _InstanceCreateInfo(ctypes.Structure):
    _fields_ = [("sType", ctypes.c_int), ("pNext", ctypes.c_void_p), ("flags", ctypes.c_uint32),
                ("pApplicationInfo", ctypes.POINTER(_ApplicationInfo)),
                ("enabledLayerCount", ctypes.c_uint32), ("ppEnabledLayerNames", ctypes.c_void_p),
                ("enabledExtensionCount", ctypes.c_uint32), ("ppEnabledExtensionNames", ctypes.c_void_p)]


def vulkan_devices() -> list[tuple[str, int]]:
    """[(deviceName, deviceType)] of every Vulkan physical device, [] without a Vulkan loader."""
    try:
        vk = ctypes.CDLL(ctypes.util.find_library("vulkan") or "libvulkan.so.1")
    except OSError:
        return []
    pointer = ctypes.c_void_p
    vk.vkCreateInstance.argtypes = [pointer, pointer, pointer]
    vk.vkEnumeratePhysicalDevices.argtypes = [pointer, pointer, pointer]
    vk.vkGetPhysicalDeviceProperties.argtypes = [pointer, pointer]
    vk.vkDestroyInstance.argtypes = [pointer, pointer]
    application = _ApplicationInfo(0, None, b"softfem", 0, None, 0, 1 << 22)   # Vulkan 1.0
    create = _InstanceCreateInfo(1, None, 0, ctypes.pointer(application), 0, None, 0, None)
    instance = ctypes.c_void_p()
    if vk.vkCreateInstance(ctypes.byref(create), None, ctypes.byref(instance)) != 0:
        return []
    try:
        count = ctypes.c_uint32()
        vk.vkEnumeratePhysicalDevices(instance, ctypes.byref(count), None)
        handles = (ctypes.c_void_p * count.value)()
        vk.vkEnumeratePhysicalDevices(instance, ctypes.byref(count), handles)
        devices = []
        for handle in handles[:count.value]:
            # VkPhysicalDeviceProperties: four uint32, deviceType at byte 16, deviceName[256] at 20.
            properties = ctypes.create_string_buffer(4096)
            vk.vkGetPhysicalDeviceProperties(handle, properties)
            kind = int.from_bytes(properties.raw[16:20], sys.byteorder)
            name = properties.raw[20:276].split(b"\0", 1)[0].decode(errors="replace")
            devices.append((name, kind))
        return devices
    finally:
        vk.vkDestroyInstance(instance, None)
