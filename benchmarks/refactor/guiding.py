"""Dwivedi sampling (``volpath_delta``'s ``guiding``, issue 29), measured before it was
removed: relative variance per render of the tuning half's homogeneous spheres and of an
isotropic dense sphere (the scheme's best case), and its mean at finite depths (where
the weights are bounded, so the means can be compared) against the unguided walk.

    python3 benchmarks/refactor/guiding.py
"""
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
import mitsuba_plugins  # noqa: E402,F401  -- chooses libLLVM before drjit loads
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant("llvm_ad_rgb")
import dense_heldout  # noqa: E402

SEEDS, SPP = 16, 32
SPHERES = ("tuning04_sphere_spot", "tuning12_sphere_area", "tuning20_sphere_env")


def sphere(albedo: float, g: float, sigma_t: float, light: str) -> mi.Scene:
    d = {"type": "scene",
         "medium": {"type": "homogeneous", "id": "m", "sigma_t": sigma_t,
                    "albedo": {"type": "rgb", "value": albedo}, "phase": {"type": "hg", "g": g}},
         "sphere": {"type": "sphere", "bsdf": {"type": "null"},
                    "interior": {"type": "ref", "id": "m"}},
         "sensor": {"type": "perspective", "fov": 30,
                    "to_world": mi.ScalarTransform4f().look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 16, "height": 16,
                             "rfilter": {"type": "box"}}}}
    if light == "env":
        d["light"] = {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}
    else:
        d["light"] = {"type": "point", "position": [1, 2, 3],
                      "intensity": {"type": "rgb", "value": 10.0}}
    return mi.load_dict(d)


def measure(scene, guiding: float, max_depth: int = -1, spp: int = SPP):
    """(mean, its standard error over seeds, relative variance of one render, seconds)."""
    integ = mi.load_dict({"type": "volpath_delta", "guiding": guiding, "max_depth": max_depth})
    mi.render(scene, integrator=integ, spp=spp, seed=10 ** 6)     # compile
    t0 = time.perf_counter()
    a = np.stack([np.array(mi.render(scene, integrator=integ, spp=spp, seed=s))
                  for s in range(SEEDS)])
    seconds = time.perf_counter() - t0
    m = a.mean(0)
    rel_var = float(np.mean(a.var(0, ddof=1) / (m ** 2 + 1e-2)))
    return a.mean(), a.mean((1, 2, 3)).std(ddof=1) / np.sqrt(SEEDS), rel_var, seconds


def row(label, scene, settings, **kw):
    for s in settings:
        mean, err, rv, sec = measure(scene, s, **kw)
        print(f"{label} guiding {s:g}: mean {mean:.5f} +- {err:.5f}, relative variance "
              f"{rv:.4g}, {sec:.2f} s", flush=True)


def main() -> None:
    cases = {c.name: c for c in dense_heldout.family()}
    tmp = Path(tempfile.mkdtemp())
    for name in SPHERES:
        row(name, dense_heldout.scene(cases[name], 32, tmp), (0.0, 0.25, 0.5))
    for light in ("env", "point"):
        row(f"isotropic sphere, albedo 0.99, sigma_t 40, {light}",
            sphere(0.99, 0.0, 40.0, light), (0.0, 0.5, 0.8))
    for depth in (3, 6):
        row(f"HG g 0.7 sphere, albedo 0.9, sigma_t 20, env, max_depth {depth}",
            sphere(0.9, 0.7, 20.0, "env"), (0.0, 0.5), max_depth=depth, spp=1024)


if __name__ == "__main__":
    main()
