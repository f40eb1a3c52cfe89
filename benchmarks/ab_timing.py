"""Does a change alter speed? Median time per render (64^2, 32 spp, 9 renders after a
warm-up) of the media and surface configurations, for whichever checkout Python imports;
prints JSON.

To compare two checkouts, run it alternately in separate processes, three times each,
and compare the medians: the change's checkout with ``python3 -m benchmarks.ab_timing``
from its root; an older one from its own root with its ``integrators/`` and ``media/``
linked under its ``mitsuba_plugins/`` and ``PYTHONPATH`` set to that root (the
editable install then does not shadow it)."""
from __future__ import annotations

import json
import os
import statistics
import time
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import drjit as dr
import mitsuba as mi

mi.set_variant(os.environ.get("MITSUBA_PLUGINS_VARIANT") or "llvm_ad_rgb")
CONFIGS = [("smoke", {"type": "volpath_delta"}), ("sparse", {"type": "volpath_delta"}),
           ("chromatic", {"type": "volpath_delta"}),
           ("sparse", {"type": "volpath_delta", "transmittance": "ratio"}),
           ("smoke", {"type": "volpath_raymarch"}),
           ("sparse", {"type": "volpath_raymarch", "mode": "single"}),
           ("cornell_box", {"type": "path_rr"})]


def main() -> dict:
    out = {}
    for name, spec in CONFIGS:
        scene = mi.load_file(str(Path.cwd() / "scenes" / f"{name}.xml"), res="64")
        integrator = mi.load_dict(spec)
        mi.render(scene, integrator=integrator, spp=4, seed=0)      # compiles
        times = []
        for k in range(9):
            t0 = time.perf_counter()
            img = mi.render(scene, integrator=integrator, spp=32, seed=k + 1)
            dr.eval(img)
            dr.sync_thread()
            times.append(time.perf_counter() - t0)
        out[f"{name}:{json.dumps(spec, sort_keys=True)}"] = statistics.median(times)
    return out


if __name__ == "__main__":
    print(json.dumps(main(), indent=1))
