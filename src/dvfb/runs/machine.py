"""What a run's ``meta.json`` records about the machine and the software it ran on, so that a
researcher can tell why two machines give different numbers (docs/runs.md): the versions of the
libraries that decide the numerics, the CPU model with its vector extensions (float32 sums are
ordered differently with AVX2 and AVX-512, docs/members.md), and the GPUs torch sees."""

from __future__ import annotations

import os
import platform
from importlib import metadata

import torch

# The distributions whose versions change numbers: the maths, the physics and the environments.
LIBRARIES = ("torch", "numpy", "mujoco", "dm_control", "scipy")
# The CPU flags that change which kernels run (and so the rounding of sums).
VECTOR_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512_bf16", "avx512_vnni", "amx_bf16", "amx_tile")


def _version(distribution: str) -> str | None:
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return None


def cores() -> int:
    """The CPUs this process may run on (a SLURM job's allocation, not the machine's cores)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def cpu() -> dict:
    """The CPU model, its vector extensions (Linux's /proc/cpuinfo) and the kernels torch picked."""
    model, flags = platform.processor() or None, set()
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as file:
            for line in file:
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "model name":
                    model = value.strip()
                elif key == "flags":
                    flags = set(value.split())
                    break
    except OSError:
        pass
    return {"model": model, "vector_extensions": [f for f in VECTOR_FLAGS if f in flags],
            "torch_capability": torch.backends.cpu.get_cpu_capability()}


def describe() -> dict:
    """Python, library versions, CPU and GPUs, as meta.json records them."""
    gpus = ([torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
            if torch.cuda.is_available() else [])
    return {"python": platform.python_version(),
            "versions": {name: _version(name) for name in LIBRARIES},
            "cpu": cpu(), "gpus": gpus}
