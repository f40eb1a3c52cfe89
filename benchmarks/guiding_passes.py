"""Where a guided render's time goes, pass by pass (issue 47; docs/benchmarks.md, "Guiding
on a GPU").

``python3 -m benchmarks.guiding_passes SCENE RES SPP [--slots 4,2,1]``: for one scene of
:data:`benchmarks.guiding.SCENES`, the unguided render and guided renders with each
reservoir size (``guiding.sampling.SLOTS``, records per path) and with and without
``guiding_distance``; per render its wall time, its passes and each pass's kernel time
(Dr.Jit's kernel history; the second of two renders, so no compilation). Prints only.
"""
from __future__ import annotations

import argparse
import time

from benchmarks import guiding
from benchmarks.harness import jit_kernels
import drjit as dr
import mitsuba as mi

from mitsuba_plugins.guiding import sampling


def _slots(n: int) -> None:
    """Reservoirs of ``n`` vertices from the next render on (its loop state changes)."""
    sampling.SLOTS = n
    sampling.Records.DRJIT_STRUCT = sampling._fields()


def profile(scene: mi.Scene, label: str, config: dict, spp: int) -> None:
    integrator = mi.load_dict(config)
    for seed in range(2):
        dr.sync_thread()
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        start = time.perf_counter()
        dr.eval(mi.render(scene, integrator=integrator, spp=spp, seed=seed))
        dr.sync_thread()
        wall = time.perf_counter() - start
        history = jit_kernels()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    report = getattr(integrator, "guiding_report", None)
    kernels = [round(k["execution_time"], 1) for k in history if k["execution_time"] > 0.05]
    print(f"{label:30s} wall {wall * 1e3:7.1f} ms  passes {report.passes if report else [spp]}"
          f"  kernels [ms] {kernels}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", choices=sorted(guiding.SCENES))
    ap.add_argument("res", type=int)
    ap.add_argument("spp", type=int)
    ap.add_argument("--slots", default=str(sampling.SLOTS))
    args = ap.parse_args()
    scene = guiding.SCENES[args.scene][1](args.res)
    default = sampling.SLOTS
    profile(scene, "off", {"type": "volpath_delta"}, args.spp)
    for n in (int(s) for s in args.slots.split(",")):
        _slots(n)
        for distance in (True, False):
            profile(scene, f"guided, {n} slots" + ("" if distance else ", no distance"),
                    {"type": "volpath_delta", "guiding": "volumes",
                     "guiding_distance": distance}, args.spp)
    _slots(default)


if __name__ == "__main__":
    main()
