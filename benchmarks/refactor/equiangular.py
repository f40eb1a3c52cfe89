"""Equiangular sampling toward point and spot lights (issue 29 experiment): bias and
efficiency of ``volpath_delta`` with ``equiangular`` on against off (and Mitsuba's
``volpath``) on a fog cube lit by a light inside it, at several extinctions.

    python3 benchmarks/refactor/equiangular.py [sigma_t,...] [--seeds N] [--spp S]

Per configuration: the mean of the image over N seeds (and its z against ``off``: the
difference over the standard error of the difference of the two means), the relative
variance of one render (the per-pixel variance over seeds over the squared reference
mean, averaged), the median time of a render, and the efficiency (1 / (relvar x time))
over ``off``'s.
"""
from __future__ import annotations

import argparse
import time

import mitsuba_plugins  # noqa: F401  (finds libLLVM, registers the plugins)
import mitsuba as mi
import numpy as np

mi.set_variant("llvm_ad_rgb")

CONFIGS = {"off": {"type": "volpath_delta"},
           "eq": {"type": "volpath_delta", "equiangular": True},
           "volpath": {"type": "volpath"}}


def fog(sigma_t: float, light: str) -> mi.Scene:
    lights = {"point": {"type": "point", "position": [0.3, 0.2, 0.0],
                        "intensity": {"type": "rgb", "value": 5.0}},
              "spot": {"type": "spot", "cutoff_angle": 35,
                       "to_world": mi.ScalarTransform4f().look_at([0.3, 0.8, 0], [0, -1, 0],
                                                                  [0, 0, 1]),
                       "intensity": {"type": "rgb", "value": 20.0}}}
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0.3, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "box": {"type": "cube", "bsdf": {"type": "null"},
                "interior": {"type": "homogeneous", "sigma_t": sigma_t,
                             "albedo": {"type": "rgb", "value": [0.9, 0.8, 0.7]},
                             "phase": {"type": "hg", "g": 0.3}}},
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"},
                  "to_world": mi.ScalarTransform4f().translate([0, -1, 0]).rotate(
                      [1, 0, 0], -90).scale(3)},
        "light": lights[light]})


def run(scene, cfg, seeds, spp, base):
    integrator = mi.load_dict(cfg)
    mi.render(scene, integrator=integrator, spp=spp, seed=base)     # compile
    images, times = [], []
    for s in range(seeds):
        t0 = time.perf_counter()
        img = mi.render(scene, integrator=integrator, spp=spp, seed=base + 1 + s)
        images.append(np.array(img))
        times.append(time.perf_counter() - t0)
    return np.array(images), float(np.median(times))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("sigmas", nargs="?", default="0.3,1,3")
    ap.add_argument("--lights", default="point,spot")
    ap.add_argument("--seeds", type=int, default=24)
    ap.add_argument("--spp", type=int, default=32)
    args = ap.parse_args()
    for light in args.lights.split(","):
        for sigma in map(float, args.sigmas.split(",")):
            scene = fog(sigma, light)
            res = {k: run(scene, c, args.seeds, args.spp, 1000 * i)
                   for i, (k, c) in enumerate(CONFIGS.items())}
            ref = np.mean([r[0].mean(0) for r in res.values()], axis=0)
            a, _ = res["off"]
            row = []
            for k, (imgs, t) in res.items():
                m = imgs.mean(axis=(1, 2, 3))
                z = (m.mean() - a.mean(axis=(1, 2, 3)).mean()) / np.sqrt(
                    (m.var(ddof=1) + a.mean(axis=(1, 2, 3)).var(ddof=1)) / len(m) + 1e-30)
                relvar = float(np.mean(imgs.var(0, ddof=1) / (ref ** 2 + 1e-4)))
                row.append((k, m.mean(), z, relvar, t))
            eff_off = 1 / (row[0][3] * row[0][4])
            print(f"{light} sigma_t {sigma:g}: " + "; ".join(
                f"{k} mean {m:.4f} (z {z:+.1f}) relvar {v:.4f} time {1e3 * t:.0f} ms "
                f"eff {1 / (v * t) / eff_off:.2f}" for k, m, z, v, t in row), flush=True)


if __name__ == "__main__":
    main()
