"""grid_medium benchmark: volpath time with grid_medium vs heterogeneous, peak memory of a
256^3 grid, majorant-grid build time.

1. Time: each medium scene and its ``*_heterogeneous`` twin rendered by Mitsuba's
   ``volpath`` in one process, warmed up, alternating, median of ``--runs``.
2. Memory: a fresh process per configuration loads a scene with a 256^3 grid (or a
   2^3 one: the baseline), renders 16x16 at 4 spp, and reports how far the peak RSS
   (VmHWM, reset after import) rose above the RSS before loading.
   Target: peak - baseline <= 1.5 x the raw float32 grid (64 MiB).
3. Build: MajorantBuilder over an in-memory 256^3 grid (target < 1 s), and the whole
   ``grid_medium`` load (read, validate, upload, build).

Writes ``benchmarks/results/grid_medium.{md,json}``.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
from mitsuba_plugins import output
import mitsuba as mi
import numpy as np

from benchmarks.harness import cpu_model, status_mib, timed_render

ROOT = Path(__file__).resolve().parents[1]
SCENES = ["smoke", "sparse", "chromatic"]
MEM_RES = 256


def bench_time(name, res, spp, runs):
    scenes = {k: mi.load_file(str(ROOT / "scenes" / f"{name}{suffix}.xml"), res=str(res),
                              spp=str(spp))
              for k, suffix in (("grid_medium", ""), ("heterogeneous", "_heterogeneous"))}
    for k, scene in scenes.items():
        timed_render(scene, scene.integrator(), spp, seed=10 ** 6)  # compile
    times = {k: [] for k in scenes}
    for run in range(runs):
        order = list(scenes) if run % 2 == 0 else list(reversed(scenes))
        for k in order:
            t, _ = timed_render(scenes[k], scenes[k].integrator(), spp, seed=run)
            times[k].append(t)
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"times_s": times, "median_s": med,
            "time_ratio": med["grid_medium"] / med["heterogeneous"]}


def _memory_child(kind: str, path: str) -> None:
    """Run in a fresh process: load + render; print the rise of peak RSS over the RSS
    before loading (MiB; the high-water mark is reset first, so import-time peaks do
    not hide the load) and the load time."""
    Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
    before = status_mib("VmRSS")
    medium = {"grid_medium": {"type": "grid_medium", "filename": path, "scale": 20.0},
              "heterogeneous": {"type": "heterogeneous", "scale": 20.0,
                                "sigma_t": {"type": "gridvolume", "filename": path}}}[kind]
    t0 = time.perf_counter()
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "volpath", "max_depth": 4},
        "env": {"type": "constant"},
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 16,
                                                   "height": 16}},
        "box": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium,
                "to_world": mi.ScalarTransform4f().translate([0, 0, 5])}})
    load_s = time.perf_counter() - t0
    np.array(mi.render(scene, spp=4))
    peak = status_mib("VmHWM") - before
    print(json.dumps({"peak_mib": peak, "load_s": load_s}))


def _run_child(kind, path):
    out = subprocess.run([sys.executable, "-m", __spec__.name,
                           "--memory-child", kind, path],
                         check=True, capture_output=True, text=True, cwd=ROOT)
    return json.loads(out.stdout.strip().splitlines()[-1])


def bench_memory(workdir: Path):
    from mitsuba_plugins.grids.gridio import write_vol
    rng = np.random.default_rng(0)
    big = workdir / "big.vol"
    write_vol(big, rng.random((MEM_RES,) * 3, dtype=np.float32))
    tiny = workdir / "tiny.vol"
    write_vol(tiny, rng.random((2, 2, 2), dtype=np.float32))
    raw = MEM_RES ** 3 * 4 / 2 ** 20
    out = {"raw_mib": raw}
    for kind in ("grid_medium", "heterogeneous"):
        base = _run_child(kind, str(tiny))
        full = _run_child(kind, str(big))
        out[kind] = {"baseline_mib": base["peak_mib"], "peak_mib": full["peak_mib"],
                     "extra_over_raw": (full["peak_mib"] - base["peak_mib"]) / raw,
                     "load_s": full["load_s"]}
    return out


def bench_build(runs=5):
    from mitsuba_plugins.grids.bounds import MajorantBuilder, resolution_for
    data = np.random.default_rng(1).random((MEM_RES,) * 3 + (1,), dtype=np.float32)
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        MajorantBuilder(data.shape, resolution_for(data.shape, 16)).add_all(data).finish()
        times.append(time.perf_counter() - t0)
    return {"median_s": statistics.median(times), "times_s": times}


def write_results(result, out_dir: Path):
    out_dir.mkdir(parents=True, exist_ok=True)
    output.write_json(out_dir / "grid_medium.json", result, indent=2)
    t, m, b = result["time"], result["memory"], result["build"]
    lines = [
        "# grid_medium benchmark",
        "",
        f"{result['date']}, {result['cpu']} ({result['cores']} cores), Mitsuba "
        f"{result['mitsuba']}, variant {result['variant']}. Command: "
        "`python -m benchmarks.grid_medium`.",
        "",
        f"## Mitsuba's volpath: grid_medium vs heterogeneous ({result['res']}^2, "
        f"{result['spp']} spp, median of {result['runs']} alternating warm renders)",
        "",
        "| scene | grid_medium (s) | heterogeneous (s) | time ratio (target <= 1.10) |",
        "|---|---|---|---|",
    ]
    for name, r in t.items():
        lines.append(f"| {name} | {r['median_s']['grid_medium']:.3f} | "
                     f"{r['median_s']['heterogeneous']:.3f} | {r['time_ratio']:.3f} |")
    lines += [
        "",
        f"## Peak memory, {MEM_RES}^3 float32 grid (raw {m['raw_mib']:.0f} MiB), fresh "
        "process, load + 16x16 render",
        "",
        "| medium | baseline rise (2^3 grid) MiB | peak rise MiB | (peak - baseline) / raw | load s |",
        "|---|---|---|---|---|",
    ]
    for kind in ("grid_medium", "heterogeneous"):
        r = m[kind]
        lines.append(f"| {kind} | {r['baseline_mib']:.0f} | {r['peak_mib']:.0f} | "
                     f"{r['extra_over_raw']:.2f} | {r['load_s']:.2f} |")
    lines += [
        "",
        "Target: grid_medium (peak - baseline) / raw <= 1.5.",
        "",
        f"## Majorant grid build, {MEM_RES}^3 -> 16^3: median {b['median_s'] * 1000:.0f} ms "
        "(target < 1 s)",
        "",
    ]
    output.write_text(out_dir / "grid_medium.md", "\n".join(lines))
    print("\n".join(lines))


def main():
    if len(sys.argv) == 4 and sys.argv[1] == "--memory-child":
        mi.set_variant(os.environ.get("MI_VARIANT", "llvm_ad_rgb"))
        _memory_child(sys.argv[2], sys.argv[3])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = ap.parse_args()
    mi.set_variant(args.variant)
    os.environ["MI_VARIANT"] = args.variant
    result = {"date": datetime.date.today().isoformat(), "cpu": cpu_model(),
              "cores": os.cpu_count(), "mitsuba": mi.__version__, "variant": args.variant,
              "res": args.res, "spp": args.spp, "runs": args.runs}
    result["build"] = bench_build()
    with tempfile.TemporaryDirectory() as tmp:
        result["memory"] = bench_memory(Path(tmp))
    result["time"] = {name: bench_time(name, args.res, args.spp, args.runs) for name in SCENES}
    write_results(result, Path(args.out))


if __name__ == "__main__":
    main()
