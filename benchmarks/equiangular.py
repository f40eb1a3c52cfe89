"""Equiangular sampling (``volpath_delta``'s ``equiangular``): where it pays.

A fog cube (side 2, albedo 0.9/0.8/0.7, HG g 0.3) over a diffuse floor, lit by a point
light or a spot light inside it, off centre; extinctions ``--sigmas``. Configurations:
``volpath_delta`` with ``equiangular`` off and on, and Mitsuba's ``volpath``. Each
renders ``--runs`` images of ``--spp`` at 32x32 with disjoint seeds, the configurations
alternating (benchmarks/harness.py), after a warm-up render each.

Reported per configuration: the image mean with its z against ``off`` (difference of the
means over its standard error: the check that both estimate one image), the relative
variance of one render (per-pixel variance over the runs divided by the squared mean of
all configurations' images, averaged over pixels and channels), the median time of a
render, and the efficiency 1 / (relative variance x time) over ``off``'s and over
``volpath``'s. The off estimator's variance is heavy-tailed here (rare collisions next to
the light): with 24 runs it read 0.26, with 200 runs 0.65 (point light, sigma_t 0.3), so
use many runs.

``python3 -m benchmarks.equiangular`` writes ``benchmarks/results/equiangular.{md,json}``.
"""
from __future__ import annotations

import argparse
import datetime
import json
import sys
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import mitsuba as mi
import numpy as np

mi.set_variant("llvm_ad_rgb")
from benchmarks.harness import alternate, device_model, timed_render

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = {"off": {"type": "volpath_delta"},
           "equiangular": {"type": "volpath_delta", "equiangular": True},
           "volpath": {"type": "volpath"}}
LIGHTS = {
    "point": {"type": "point", "position": [0.3, 0.2, 0.0],
              "intensity": {"type": "rgb", "value": 5.0}},
    "spot": {"type": "spot", "cutoff_angle": 35,
             "to_world": mi.ScalarTransform4f().look_at([0.3, 0.8, 0], [0, -1, 0], [0, 0, 1]),
             "intensity": {"type": "rgb", "value": 20.0}},
}


def fog(sigma_t: float, light: str, res: int) -> mi.Scene:
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0.3, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "box": {"type": "cube", "bsdf": {"type": "null"},
                "interior": {"type": "homogeneous", "sigma_t": sigma_t,
                             "albedo": {"type": "rgb", "value": [0.9, 0.8, 0.7]},
                             "phase": {"type": "hg", "g": 0.3}}},
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"},
                  "to_world": mi.ScalarTransform4f().translate([0, -1, 0]).rotate(
                      [1, 0, 0], -90).scale(3)},
        "light": LIGHTS[light]})


def measure(scene, runs: int, spp: int) -> dict:
    integrators = {k: mi.load_dict(c) for k, c in CONFIGS.items()}
    for k, integrator in integrators.items():
        timed_render(scene, integrator, spp, 10**6)                  # compile
    times, images = alternate(integrators, runs, lambda k, run: timed_render(
        scene, integrators[k], spp, 1000 * list(integrators).index(k) + run))
    ref = np.mean([np.mean(images[k], axis=0) for k in integrators], axis=0)
    means = {k: np.mean(images[k], axis=(1, 2, 3)) for k in integrators}
    out = {}
    for k in integrators:
        m, m0 = means[k], means["off"]
        se = np.sqrt((m.var(ddof=1) + m0.var(ddof=1)) / runs)
        relvar = float(np.mean(np.var(images[k], axis=0, ddof=1) / (ref ** 2 + 1e-4)))
        out[k] = {"mean": float(m.mean()), "z_vs_off": float((m.mean() - m0.mean()) / se)
                  if k != "off" else 0.0, "relvar": relvar, "time": float(np.median(times[k]))}
    for k in out:
        eff = 1 / (out[k]["relvar"] * out[k]["time"])
        out[k]["eff_vs_off"] = eff * out["off"]["relvar"] * out["off"]["time"]
        out[k]["eff_vs_volpath"] = eff * out["volpath"]["relvar"] * out["volpath"]["time"]
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sigmas", default="0.3,1,3,10")
    ap.add_argument("--lights", default="point,spot")
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "equiangular"))
    args = ap.parse_args()
    rows = {}
    for light in args.lights.split(","):
        for sigma in map(float, args.sigmas.split(",")):
            r = measure(fog(sigma, light, args.res), args.runs, args.spp)
            rows[f"{light} {sigma:g}"] = r
            print(f"{light} sigma_t {sigma:g}: " + "; ".join(
                f"{k} z {v['z_vs_off']:+.1f} relvar {v['relvar']:.3f} "
                f"{1e3 * v['time']:.1f} ms eff/off {v['eff_vs_off']:.2f} "
                f"eff/volpath {v['eff_vs_volpath']:.2f}" for k, v in r.items()), flush=True)
    meta = {"date": datetime.date.today().isoformat(), "cpu": device_model(mi.variant()),
            "variant": mi.variant(), "argv": " ".join(sys.argv[1:]), "rows": rows}
    Path(args.out + ".json").write_text(json.dumps(meta, indent=1))
    lines = ["# Equiangular sampling: where it pays\n",
             f"Measured {meta['date']} on {meta['cpu']} ({meta['variant']}) by `python3 -m "
             f"benchmarks.equiangular {meta['argv']}` ({args.runs} alternating runs of "
             f"{args.spp} spp at {args.res}x{args.res}; method: the script's docstring).\n",
             "| light, sigma_t | config | mean (z vs off) | relvar | time (ms) | "
             "eff / off | eff / volpath |", "|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        for k, v in r.items():
            lines.append(f"| {name} | {k} | {v['mean']:.4f} ({v['z_vs_off']:+.1f}) | "
                         f"{v['relvar']:.3f} | {1e3 * v['time']:.1f} | {v['eff_vs_off']:.2f} | "
                         f"{v['eff_vs_volpath']:.2f} |")
    Path(args.out + ".md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
