"""Sparse against dense storage of the same grid, in any variant (no OpenVDB needed):
the cloud of benchmarks/cloud.py written as an n^3 .npy, loaded by grid_medium with
``storage = dense`` and ``sparse`` in one process; load time, and time per sample of
volpath_delta and volpath_raymarch (256x256 at 16 spp, alternating, median of 5 after a
warm-up). ``scenes``: the same for scenes/smoke.xml, sparse.xml and chromatic.xml (their
``storage`` parameter; 128x128). Target (issue 13): sparse <= 1.3x dense.

    MITSUBA_PLUGINS_VARIANT=cuda_ad_rgb python3 -m benchmarks.sparse_vs_dense 256,512
    python3 -m benchmarks.sparse_vs_dense scenes

Prints its table (committed figures: docs/benchmarks.md).
"""
import statistics
import sys
import tempfile
import time
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import drjit as dr
import mitsuba as mi

from mitsuba_plugins.registry import default_variant

mi.set_variant(default_variant())
mi.set_log_level(mi.LogLevel.Error)
from benchmarks.cloud import scene_dict, write_npy
from benchmarks.harness import timed_render

RES, SPP, RUNS = 256, 16, 5
ROOT = Path(__file__).resolve().parents[1]


def compare(label: str, scenes: dict, load: dict) -> None:
    """Time per sample of both integrators on ``scenes`` {"dense": .., "sparse": ..}."""
    for name in ("volpath_delta", "volpath_raymarch"):
        spec = {"type": name, "max_depth": 16}
        if name == "volpath_raymarch":
            spec["step_size"] = 2.0 / 256
        integrator = mi.load_dict(spec)
        times = {s: [] for s in scenes}
        for s in scenes:
            timed_render(scenes[s], integrator, SPP, 0)
        for run in range(RUNS):
            for s in scenes:
                times[s].append(timed_render(scenes[s], integrator, SPP, run + 1)[0])
        film = scenes["dense"].sensors()[0].film().size()
        ns = {s: statistics.median(v) / (film[0] * film[1] * SPP) * 1e9 for s, v in times.items()}
        print(f"{mi.variant()} {label} {name}: ns/sample dense {ns['dense']:.2f} sparse "
              f"{ns['sparse']:.2f} ratio {ns['sparse'] / ns['dense']:.2f}; load s dense "
              f"{load['dense']:.2f} sparse {load['sparse']:.2f}", flush=True)


def timed_load(load, *args, **kw):
    t0 = time.perf_counter()
    scene = load(*args, **kw)
    dr.sync_thread()
    return scene, time.perf_counter() - t0


def scenes() -> None:
    for name in ("smoke", "sparse", "chromatic"):
        loaded = {s: timed_load(mi.load_file, str(ROOT / "scenes" / f"{name}.xml"), res="128",
                                storage=s) for s in ("dense", "sparse")}
        compare(name, {s: v[0] for s, v in loaded.items()}, {s: v[1] for s, v in loaded.items()})


def main(sizes: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        for n in map(int, sizes.split(",")):
            path = str(Path(tmp) / f"cloud{n}.npy")
            write_npy(n, path)
            loaded = {}
            for storage in ("dense", "sparse"):
                medium = {"type": "grid_medium", "filename": path, "albedo": 0.8,
                          "storage": storage,
                          "to_world": mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)}
                loaded[storage] = timed_load(mi.load_dict, scene_dict(medium, RES, mi))
            compare(f"{n}^3", {s: v[0] for s, v in loaded.items()},
                    {s: v[1] for s, v in loaded.items()})


if __name__ == "__main__":
    arg = sys.argv[1] if len(sys.argv) > 1 else "256,512"
    scenes() if arg == "scenes" else main(arg)
