"""Does a change alter any image? Fixed-seed renders of every code path of the plugins
(each integrator and estimator option, dense/sparse/chromatic/heterogeneous/emissive
media, surfaces only, a light in fog, the refined "hot" cells, and the gradients of both
gradient estimators), saved before a change (``capture DIR``) and compared after it
(``check DIR``). On the LLVM backend one worker thread runs them, so renders that draw
the same random numbers agree bit for bit (worst 0); with several threads, atomic adds
in varying order leave up to ~5e-7 relative.

Run from the repository root::

    python3 -m benchmarks.identity capture /tmp/before   # before the change
    python3 -m benchmarks.identity check /tmp/before     # after it: prints the worst

Only public interfaces are used (scene files, ``mi.render``, ``mi.traverse``), so the
same script captures from an older checkout.
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import drjit as dr
import mitsuba as mi
import numpy as np

mi.set_variant(os.environ.get("MITSUBA_PLUGINS_VARIANT") or "llvm_ad_rgb")
if mi.variant().startswith("llvm"):
    # one worker thread: the film's and the gradients' atomic adds then run in one
    # order, so equal random numbers give equal bits (with more threads ~4e-7 apart)
    dr.set_thread_count(1)
SCENES = Path.cwd() / "scenes"   # run from the root of the checkout under test
#: differences below this (relative, floor 1e-3) are the film's atomic-add order
TOLERANCE = 1e-5


def load(name: str):
    return mi.load_file(str(SCENES / f"{name}.xml"), res="24")


def light_in_fog():
    """A ball of homogeneous fog holding a point light (equiangular sampling's case)."""
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 38,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0.6, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 24, "height": 24, "rfilter": {"type": "box"}}},
        "ball": {"type": "sphere", "bsdf": {"type": "null"},
                 "interior": {"type": "homogeneous", "sigma_t": 0.8, "albedo": 0.9,
                              "phase": {"type": "hg", "g": 0.3}}},
        "lamp": {"type": "point", "position": [0.2, 0.1, 0.3],
                 "intensity": {"type": "rgb", "value": 3.0}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 0.4}},
    })


CONFIGS = []
for scene in ("smoke", "sparse", "chromatic"):
    for tr in ("track_length", "ratio", "residual"):
        CONFIGS.append((scene, {"type": "volpath_delta", "transmittance": tr}))
    for mode in ("multi", "single"):
        for sm in ("fixed", "majorant"):
            CONFIGS.append((scene, {"type": "volpath_raymarch", "mode": mode, "step_mode": sm}))
for scene in ("smoke_heterogeneous", "chromatic_heterogeneous"):
    CONFIGS.append((scene, {"type": "volpath_delta"}))
    CONFIGS.append((scene, {"type": "volpath_raymarch"}))
for scene in ("furnace_env", "cornell_box"):
    CONFIGS.append((scene, {"type": "volpath_delta"}))
    CONFIGS.append((scene, {"type": "volpath_raymarch", "mode": "single"}))
CONFIGS += [
    ("smoke", {"type": "volpath_delta", "free_flight": "decomposition"}),
    ("chromatic", {"type": "volpath_delta", "free_flight": "decomposition"}),
    ("smoke", {"type": "volpath_delta", "shadow_roulette": 0.0, "rr_max_survival": 0.95}),
    ("fire", {"type": "volpath_delta"}),
    ("fire", {"type": "volpath_raymarch"}),
    ("sparse_heterogeneous", {"type": "volpath_delta"}),
    ("cornell_box", {"type": "path_rr"}),
    ("cornell_box", {"type": "path_rr", "emitter_selection": "power", "rr_rule": "fixed"}),
    ("veach_mis", {"type": "path_rr"}),
    ("veach_mis", {"type": "direct_mis"}),
    ("cornell_box", {"type": "direct_mis"}),
    (light_in_fog, {"type": "volpath_delta", "equiangular": True}),
    (light_in_fog, {"type": "volpath_delta"}),
]
#: the same smoke with every cell "hot" (refined pieces, work budget)
HOT = [("smoke", {"type": "volpath_delta", "transmittance": tr})
       for tr in ("track_length", "ratio", "residual")]
#: backward gradients of the smoke's density grid and albedo (both gradient estimators)
GRADIENTS = [("smoke", {"type": "volpath_delta", "max_depth": 4, "gradient_estimator": g})
             for g in ("drt", "delta")]


def make_hot():
    from mitsuba_plugins import instrument
    instrument.settings.refine_optical_depth = 0.5


def image(scene, integrator) -> np.ndarray:
    scene = scene() if callable(scene) else load(scene)
    img = mi.render(scene, integrator=mi.load_dict(integrator), spp=4, seed=7)
    return np.array(img, dtype=np.float64)


def gradient(scene, integrator) -> np.ndarray:
    scene = load(scene)
    params = mi.traverse(scene)
    keys = [k for k in params.keys() if k.endswith(".data") or k.endswith(".albedo.value.value")]
    for k in keys:
        dr.enable_grad(params[k])
    params.update()
    img = mi.render(scene, params, integrator=mi.load_dict(integrator), spp=4, seed=7)
    dr.backward(dr.mean(img, axis=None))
    return np.concatenate([np.array(dr.grad(params[k]), np.float64).ravel() for k in keys])


def main(mode: str, out: str) -> float:
    os.makedirs(out, exist_ok=True)
    worst, t0 = 0.0, time.time()
    jobs = [(s, i, image) for s, i in CONFIGS] + [(s, i, gradient) for s, i in GRADIENTS] + \
        [(s, i, image) for s, i in HOT]
    for n, (scene, integrator, what) in enumerate(jobs):
        if n == len(jobs) - len(HOT):
            make_hot()
        value = what(scene, integrator)
        path = f"{out}/{n}.npy"
        name = scene.__name__ if callable(scene) else scene
        if mode == "capture":
            np.save(path, value)
            continue
        ref = np.load(path)
        floor = max(1e-3 * float(np.abs(ref).max()), 1e-30) if what is gradient else 1e-3
        rel = float((np.abs(value - ref) / np.maximum(np.abs(ref), floor)).max())
        worst = max(worst, rel)
        print(f"{what.__name__:8s} {name:24s} {integrator}: max rel {rel:.3g}"
              + ("" if rel < TOLERANCE else "  <-- DIFFERS"))
    print(f"worst {worst:.3g} over {len(jobs)} configurations, {time.time() - t0:.1f} s")
    return worst


if __name__ == "__main__":
    if len(sys.argv) != 3 or sys.argv[1] not in ("capture", "check"):
        sys.exit(__doc__)
    sys.exit(1 if main(sys.argv[1], sys.argv[2]) >= TOLERANCE else 0)
