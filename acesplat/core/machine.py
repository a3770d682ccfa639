"""What machine a number was measured on: printed beside every benchmark and profile."""

from __future__ import annotations

import os
import platform
from importlib import metadata


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


ISA_FLAGS = ("avx2", "avx512f", "avx512_bf16", "avx512_vnni", "amx_bf16")
"""x86 /proc/cpuinfo flags that change onnxruntime's kernels (FP32 and INT8 speed)."""


def cpu_isa() -> list[str]:
    """The ISA extensions of ISA_FLAGS this CPU has, plus 'neon' on ARM (AArch64 always has it); [] if unknown."""
    found: set[str] = set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                key = key.strip().lower()
                if key == "flags":  # x86
                    found |= set(ISA_FLAGS) & set(value.split())
                elif key == "features" and {"neon", "asimd"} & set(value.split()):  # ARM 32 / 64 bit
                    found.add("neon")
    except OSError:
        pass
    if platform.machine().lower() in ("aarch64", "arm64"):
        found.add("neon")
    return [f for f in (*ISA_FLAGS, "neon") if f in found]


ISA_LIMIT_VARIABLES = ("ATEN_CPU_CAPABILITY", "ONEDNN_MAX_CPU_ISA", "MKL_ENABLE_INSTRUCTIONS")
"""Environment variables that make torch's own kernels, oneDNN and MKL use less of the CPU than it has (how an
AVX2-only machine is reproduced on a bigger one)."""


def isa_limit() -> dict[str, str]:
    """The ISA_LIMIT_VARIABLES set in this process, e.g. {"ATEN_CPU_CAPABILITY": "avx2"}; {} when none is."""
    return {k: os.environ[k] for k in ISA_LIMIT_VARIABLES if os.environ.get(k)}


def bf16_units_usable() -> bool:
    """False when an ISA limit in the environment keeps torch or oneDNN below AVX-512 (bfloat16 units unused)."""
    lim = {k: v.lower() for k, v in isa_limit().items()}
    capped = lim.get("ATEN_CPU_CAPABILITY") in ("default", "avx2") or lim.get("ONEDNN_MAX_CPU_ISA", "").startswith(
        ("sse", "avx2", "avx_")
    )
    return not capped


def library_versions(
    names: tuple[str, ...] = ("numpy", "opencv-python-headless", "onnxruntime", "torch", "numba"),
) -> dict[str, str]:
    """Installed versions read from package metadata, without importing the packages (the edge has no torch)."""
    out = {}
    for n in names:
        try:
            out[n] = metadata.version(n)
        except metadata.PackageNotFoundError:
            out[n] = "not installed"
    return out


def machine_info() -> dict:
    """CPU model, logical cores, Python, OS and library versions."""
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return {
        "cpu": cpu_model(),
        "cpu_isa": cpu_isa(),
        "isa_limit": isa_limit(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "load_average_1m": round(load[0], 2),
        "libraries": library_versions(),
    }


def machine_line() -> str:
    m = machine_info()
    libs = ", ".join(f"{k} {v}" for k, v in m["libraries"].items())
    lim = "".join(f", {k}={v}" for k, v in m["isa_limit"].items())
    return f"{m['cpu']}{lim}, {m['cores']} cores, load {m['load_average_1m']}; Python {m['python']}; {libs}"
