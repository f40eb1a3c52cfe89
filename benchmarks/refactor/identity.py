"""Refactor check: fixed-seed images of every media code path, saved before a change
(``capture DIR``) and compared after it (``check DIR``): renders that draw the same random
numbers agree up to the film's atomic-add order (~1e-7 relative).

Run from the repository root: ``python3 benchmarks/refactor/identity.py capture /tmp/before``,
change the code, then ``python3 benchmarks/refactor/identity.py check /tmp/before``.
The last three configurations make every smoke cell "hot" (refined pieces, work budget)."""
import os
import sys, time
import numpy as np
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "tests"))
import mitsuba as mi
import mitsuba_plugins  # noqa
mi.set_variant("llvm_ad_rgb")
from helpers import load, render

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

HOT = [("smoke", {"type": "volpath_delta", "transmittance": tr}) for tr in ("track_length", "ratio", "residual")]
mode, out = sys.argv[1], sys.argv[2]
def make_hot():
    """Every smoke cell hot (refined pieces, work budget)."""
    try:
        from mitsuba_plugins import instrument
        instrument.settings.refine_optical_depth = 0.5
    except ImportError:          # a checkout before the instrument module
        import importlib
        for name in ("mitsuba_plugins.tracking", "mitsuba_plugins.walk",
                     "mitsuba_plugins.contract"):
            try:
                m = importlib.import_module(name)
            except ImportError:
                continue
            if hasattr(m, "REFINE_OPTICAL_DEPTH"):
                m.REFINE_OPTICAL_DEPTH = 0.5

import os; os.makedirs(out, exist_ok=True)
worst = 0
t0 = time.time()
for i, (scene, integ) in enumerate(CONFIGS + HOT):
    if i == len(CONFIGS):
        make_hot()
    img = render(load(scene, res=24), integ, spp=4, seed=7)
    f = f"{out}/{i}.npy"
    if mode == "capture":
        np.save(f, img)
    else:
        ref = np.load(f)
        rel = np.abs(img - ref) / np.maximum(np.abs(ref), 1e-3)
        worst = max(worst, rel.max())
        print(f"{scene:24s} {integ}: max rel {rel.max():.3g}" + ("" if rel.max() < 1e-5 else "  <-- DIFFERS"))
print("worst", worst, "time", time.time() - t0)
