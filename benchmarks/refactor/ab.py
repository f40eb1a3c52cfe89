"""Refactor A/B: median time per render (64^2, 32 spp, 9 renders after a warm-up) of the
media configurations, for whichever checkout Python imports; prints JSON.

To compare two checkouts, run it alternately in separate processes, e.g. with the old
checkout copied into one importable package (``integrators/`` and ``media/`` moved under
``mitsuba_plugins/``) at /tmp/oldpkg, from a folder with neither on the path:
``cd /tmp && PYTHONPATH=/tmp/oldpkg python ab.py`` then ``cd /tmp && python ab.py``
(the editable install), three times each, and compare medians."""
import os
import sys, time, statistics, json
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "tests"))
import mitsuba as mi
import mitsuba_plugins  # noqa
mi.set_variant("llvm_ad_rgb")
from helpers import load
CONFIGS = [("smoke", {"type": "volpath_delta"}), ("sparse", {"type": "volpath_delta"}),
           ("chromatic", {"type": "volpath_delta"}),
           ("sparse", {"type": "volpath_delta", "transmittance": "residual"}),
           ("smoke", {"type": "volpath_raymarch"}), ("sparse", {"type": "volpath_raymarch", "mode": "single"}),
           ("cornell_box", {"type": "path_rr"})]
out = {}
for scene_name, integ in CONFIGS:
    scene = load(scene_name, res=64)
    i = mi.load_dict(integ)
    mi.render(scene, integrator=i, spp=4, seed=0)
    ts = []
    for k in range(9):
        t0 = time.perf_counter(); img = mi.render(scene, integrator=i, spp=32, seed=k + 1); dr_img = img.numpy(); ts.append(time.perf_counter() - t0)
    out[f"{scene_name}:{integ}"] = statistics.median(ts)
print(json.dumps(out))
