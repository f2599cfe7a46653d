"""What a run's ``meta.json`` records about the machine and the software it ran on, so that a
researcher can tell why two machines give different numbers (README.md, "Using it"): the versions of the
libraries that decide the numerics, the CPU model with its vector extensions (float32 sums are
ordered differently with AVX2 and AVX-512, docs/members.md), the GPUs torch sees, the CPUs the
process may use and the torch threads it computed with.

It also decides how many CPUs a process may use (:func:`cores`: its affinity and its cgroup's CPU
quota) and the torch threads a command uses by default (:func:`default_torch_threads`, README.md,
"Threads and progress")."""

from __future__ import annotations

import math
import os
import platform
from importlib import metadata
from pathlib import Path

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
    """The CPUs this process may use: those it may run on (its affinity: a SLURM job's allocation,
    ``taskset``), at most its cgroup's CPU quota rounded up (a container's ``--cpus``, a cluster's
    CPU limit), at least one."""
    allowed = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    quota = cgroup_cpu_quota()
    return max(1, min(allowed, math.ceil(quota)) if quota is not None else allowed)


def cgroup_cpu_quota(root: str | os.PathLike = "/") -> float | None:
    """The CPU time per unit of wall time this process's cgroups allow (``2.5``: two and a half CPUs),
    the smallest along its cgroup path; None when no quota is set or the files cannot be read.

    Linux's cgroup v2 (``cpu.max``: ``QUOTA PERIOD`` or ``max PERIOD``) and v1 (``cpu.cfs_quota_us``
    and ``cpu.cfs_period_us``, quota -1 for none), found through ``/proc/self/cgroup`` under
    ``root`` (``/``; a test gives a directory laid out the same way). A container sees its own
    cgroup at the mount's top, so the mount's top directory is read as well."""
    root = Path(root)
    try:
        lines = (root / "proc/self/cgroup").read_text(encoding="utf-8").splitlines()
    except OSError:
        return None
    quotas = []
    for line in lines:
        _hierarchy, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if controllers == "":
            mounts = [root / "sys/fs/cgroup"]
        elif "cpu" in controllers.split(","):
            mounts = [root / "sys/fs/cgroup" / name for name in (controllers, "cpu", "cpu,cpuacct")]
        else:
            continue
        for mount in mounts:
            for directory in _ancestors(mount, path):
                quota = _v2_quota(directory) if controllers == "" else _v1_quota(directory)
                if quota is not None:
                    quotas.append(quota)
    return min(quotas) if quotas else None


def _ancestors(mount: Path, path: str) -> list[Path]:
    """``mount`` and every directory of ``path`` below it, the mount first."""
    out, current = [mount], mount
    for part in Path(path).parts:
        if part != "/":
            current = current / part
            out.append(current)
    return out


def _v2_quota(directory: Path) -> float | None:
    try:
        quota, period = (directory / "cpu.max").read_text(encoding="ascii").split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError, ZeroDivisionError):
        return None


def _v1_quota(directory: Path) -> float | None:
    try:
        quota = int((directory / "cpu.cfs_quota_us").read_text(encoding="ascii"))
        period = int((directory / "cpu.cfs_period_us").read_text(encoding="ascii"))
        return None if quota <= 0 or period <= 0 else quota / period
    except (OSError, ValueError):
        return None


def default_torch_threads() -> int:
    """The torch threads of a command not told how many (README.md, "Threads and progress"):
    ``OMP_NUM_THREADS`` when it is set to a positive number (what a launcher or a job script chose),
    else half the CPUs this process may use (:func:`cores`), at least one.

    Half, not all: an OpenMP thread that finds its partner descheduled waits for it at every
    operator, so more runnable threads than cores (a second command, another job) slow a run down
    many times over, while at the small preset a second thread speeds an update up by a quarter
    (bench/README.md, "Update cost of the presets")."""
    value = os.environ.get("OMP_NUM_THREADS", "").split(",")[0].strip()
    if value.isdigit() and int(value) > 0:
        return int(value)
    return max(1, cores() // 2)


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
    """Python, library versions, CPU and GPUs, the CPUs this process may use and its torch threads,
    as meta.json records them."""
    gpus = ([torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
            if torch.cuda.is_available() else [])
    return {"python": platform.python_version(),
            "versions": {name: _version(name) for name in LIBRARIES},
            "cpu": cpu(), "gpus": gpus, "cpus": cores(), "torch_threads": torch.get_num_threads()}
