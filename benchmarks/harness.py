"""What the benchmarks share: the machine's name, timed renders (synchronised), runs that
alternate between the configurations compared, and peak memory from /proc.

``benchmarks/`` is a package: each script runs as a module from the repository root
(``python3 -m benchmarks.dense``) and imports this harness, and the scene builders it
shares, as ``benchmarks.harness`` / ``benchmarks.cloud``; nothing edits ``sys.path``. It
needs a Mitsuba variant set before :func:`timed_render` is called.
"""
from __future__ import annotations

import platform
import subprocess
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def device_model(variant: str) -> str:
    """The processor that runs ``variant``: the GPU's name for a CUDA variant."""
    if variant.startswith("cuda"):
        try:
            out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                                 capture_output=True, text=True, timeout=30).stdout.strip()
            if out:
                return out.splitlines()[0] + f" (host: {cpu_model()})"
        except (OSError, subprocess.SubprocessError):
            pass
        return "NVIDIA GPU (nvidia-smi unavailable)"
    return cpu_model()


def jit_kernels() -> list:
    """The JIT kernels Dr.Jit ran since its kernel history was last read (each a dict:
    ``execution_time`` in ms, ``cache_hit``, ...); the history must be on
    (``JitFlag.KernelHistory``), and reading it waits for them."""
    return dr.kernel_history([dr.KernelType.JIT])


def timed_render(scene, integrator, spp, seed):
    t0 = time.perf_counter()
    img = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    return time.perf_counter() - t0, np.array(img)


def alternate(keys, runs: int, render):
    """``runs`` rounds of ``render(key, run) -> (seconds, image)`` over ``keys``, in order
    and reversed every other round so that drift hits every key alike; returns
    ``(times, images)``, each a dict of per-run lists."""
    keys = list(keys)
    times, images = {k: [] for k in keys}, {k: [] for k in keys}
    for run in range(runs):
        for k in (keys if run % 2 == 0 else keys[::-1]):
            t, img = render(k, run)
            times[k].append(t)
            images[k].append(img)
    return times, images


def status_mib(field: str) -> float:
    """A memory field of /proc/self/status in MiB (``VmHWM``: this process's resident
    high-water mark; unlike ``ru_maxrss`` it is not inherited across fork + exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")
