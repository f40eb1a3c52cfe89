"""Benchmark: direct_mis vs Mitsuba's direct and path_rr vs path, at equal spp.

For each scene and pair, both integrators are warmed up (compiled), then rendered
alternately A, B, A, B, ... ``--runs`` times with different seeds, each render timed with
dr.sync_thread(). Reported: median time per render, the time ratio, relative MSE (mean
over the runs) against a cached high-spp reference of the built-in, efficiency
1 / (relMSE x time) and its ratio. Results go to benchmarks/results/surface.{md,json}.

    python3 -m benchmarks.surface            # about 4 minutes on 2 cores
"""
from __future__ import annotations

import argparse
import datetime
import os
import statistics
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import drjit as dr
import mitsuba as mi
import numpy as np

from benchmarks.harness import alternate, cpu_model, timed_render
from mitsuba_plugins import output
from mitsuba_plugins.tools import stats
from mitsuba_plugins.tools.compare import cached_reference
from mitsuba_plugins.tools.scenes import load_scene

ROOT = Path(__file__).resolve().parents[1]
PAIRS = [({"type": "direct_mis"}, {"type": "direct"}), ({"type": "path_rr"}, {"type": "path"})]
SCENES = ["cornell_box", "veach_mis"]


def bench_pair(scene_name, ours, builtin, spp, runs, res, ref_spp):
    path = ROOT / "scenes" / f"{scene_name}.xml"
    scene = load_scene(str(path), res)
    ref = cached_reference(scene, str(path), res, builtin, ref_spp, ROOT / ".cache" / "references",
                           progress=False)
    integ = {"ours": mi.load_dict(ours), "builtin": mi.load_dict(builtin)}
    for k in integ:                      # warm-up: compile both kernels
        timed_render(scene, integ[k], spp, seed=10 ** 6)
    times, images = alternate(integ, runs, lambda k, run: timed_render(scene, integ[k], spp, run))
    errors = {k: [stats.rel_mse(img, ref.mean) for img in images[k]] for k in integ}
    out = {}
    for k in integ:
        t = statistics.median(times[k])
        e = float(np.mean(errors[k]))
        out[k] = {"median_s": t, "times_s": times[k], "rel_mse": e, "efficiency": stats.efficiency(e, t)}
    out["time_ratio"] = out["ours"]["median_s"] / out["builtin"]["median_s"]
    out["efficiency_ratio"] = out["ours"]["efficiency"] / out["builtin"]["efficiency"]
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    args = ap.parse_args()
    mi.set_variant(args.variant)

    results = []
    for scene_name in SCENES:
        for ours, builtin in PAIRS:
            r = bench_pair(scene_name, ours, builtin, args.spp, args.runs, args.res, args.ref_spp)
            r.update(scene=scene_name, ours_name=ours["type"], builtin_name=builtin["type"])
            results.append(r)
            print(f"{scene_name:12s} {ours['type']:10s}/{builtin['type']:6s} time ratio "
                  f"{r['time_ratio']:.3f}  efficiency ratio {r['efficiency_ratio']:.3f}", flush=True)

    meta = {"date": datetime.date.today().isoformat(), "cpu": cpu_model(), "cores": os.cpu_count(),
            "variant": args.variant, "mitsuba": mi.__version__, "drjit": dr.__version__,
            "llvm": ".".join(map(str, dr.detail.llvm_version())), "spp": args.spp,
            "res": args.res, "runs": args.runs, "ref_spp": args.ref_spp}
    out_dir = ROOT / "benchmarks" / "results"
    out_dir.mkdir(parents=True, exist_ok=True)
    output.write_json(out_dir / "surface.json", {"meta": meta, "results": results}, indent=1)
    lines = [
        "# Surface integrators vs Mitsuba built-ins",
        "",
        f"Measured {meta['date']} on {meta['cpu']} ({meta['cores']} cores), {meta['variant']}, "
        f"Mitsuba {meta['mitsuba']}, Dr.Jit {meta['drjit']}, LLVM {meta['llvm']}. "
        f"{args.res}x{args.res}, {args.spp} spp per render; median of {args.runs} alternating warm "
        f"renders; relative MSE against the built-in at {args.ref_spp} spp. "
        "Regenerate: `python3 -m benchmarks.surface`.",
        "",
        "| scene | ours / built-in | ours [s] | built-in [s] | time ratio (target <= 1.05) "
        "| rel. MSE ours | rel. MSE built-in | efficiency ratio (target >= 0.95) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(f"| {r['scene']} | {r['ours_name']} / {r['builtin_name']} | {r['ours']['median_s']:.3f} | "
                     f"{r['builtin']['median_s']:.3f} | {r['time_ratio']:.3f} | {r['ours']['rel_mse']:.3e} | "
                     f"{r['builtin']['rel_mse']:.3e} | {r['efficiency_ratio']:.3f} |")
    output.write_text(out_dir / "surface.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
