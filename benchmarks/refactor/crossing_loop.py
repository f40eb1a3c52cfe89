"""Time per sample of ``volpath_delta`` with the walk's tight crossing loop forced on over
forced off (``instrument.crossing_loop``), wall clock and kernel time, and each
medium's majorant grid and default choice, on grid scenes: ``benchmarks/dense.py``'s family,
the tuning half of ``dense_heldout.py`` (grid scenes), ``volpath_delta.py``'s sparsity
series and the shipped grid scenes. 32x32, 16 spp, two warm-up renders each, 9 renders
alternating, median over median. Issue 29 chose :data:`contract.TIGHT_LOOP_CELLS` with it.

    python3 benchmarks/refactor/crossing_loop.py [--sets dense,heldout,sparsity,scenes]
"""
import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
import mitsuba_plugins  # noqa: E402,F401  -- chooses libLLVM before drjit loads
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant("llvm_ad_rgb")
import dense  # noqa: E402
import dense_heldout  # noqa: E402
import volpath_delta  # noqa: E402
from mitsuba_plugins import instrument  # noqa: E402
from mitsuba_plugins.tracking.scene_media import SceneMedia  # noqa: E402


def scenes(sets, tmp: Path, res: int):
    if "dense" in sets:
        for case in dense.FAMILY:
            if case.shape != "homogeneous":
                yield f"dense/{case.name}", dense.scene(case, res, tmp)
    if "heldout" in sets:
        for case in dense_heldout.family():
            if case.half == "tuning" and case.shape in ("plume", "cumulus"):
                yield f"heldout/{case.name}", dense_heldout.scene(case, res, tmp)
    if "sparsity" in sets:
        for ratio in (1, 10, 30, 100):
            path = tmp / f"contrast_{ratio}.npy"
            np.save(path, volpath_delta.contrast_field(ratio))
            yield f"sparsity/{ratio}", mi.load_dict(volpath_delta._base(
                res, volpath_delta.grid_medium(str(path), 2.0)))
    if "scenes" in sets:
        for name in ("smoke", "sparse", "chromatic", "fire", "smoke_heterogeneous",
                     "sparse_heterogeneous"):
            yield f"scenes/{name}", mi.load_file(str(ROOT / "scenes" / f"{name}.xml"), res=str(res))


def cells(scene) -> str:
    trackers = SceneMedia(scene).trackers.values()
    return ",".join(f"{'x'.join(map(str, t.grid.resolution))} ({'on' if t.tight_loop else 'off'})"
                    for t in trackers) or "-"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", default="dense,heldout,sparsity,scenes")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--integrator", default='{}',
                    help="JSON of volpath_delta parameters, e.g. '{\"max_depth\": 16}'")
    args = ap.parse_args()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    integ = mi.load_dict({"type": "volpath_delta", **json.loads(args.integrator)})
    for name, scene in scenes(args.sets.split(","), Path(tempfile.mkdtemp()), args.res):
        def seconds(mode, seed):
            with instrument.crossing_loop(mode):
                dr.kernel_history()
                t0 = time.perf_counter()
                dr.eval(mi.render(scene, integrator=integ, spp=args.spp, seed=seed))
                dr.sync_thread()
                wall = time.perf_counter() - t0
                kernels = sum(k.get("execution_time", 0.0) for k in dr.kernel_history()) * 1e-3
                return wall, kernels
        for mode in (True, False):
            seconds(mode, 999), seconds(mode, 998)
        times = {True: [], False: []}
        for run in range(9):
            for mode in ((True, False) if run % 2 == 0 else (False, True)):
                times[mode].append(seconds(mode, run))
        wall = {m: statistics.median(t[0] for t in times[m]) for m in times}
        kern = {m: statistics.median(t[1] for t in times[m]) for m in times}
        print(f"{name:34s} cells {cells(scene):18s} on/off wall {wall[True] / wall[False]:.3f} "
              f"kernels {kern[True] / kern[False]:.3f}  off: wall {wall[False] * 1e3:.1f} ms, "
              f"kernels {kern[False] * 1e3:.1f} ms", flush=True)


if __name__ == "__main__":
    main()
