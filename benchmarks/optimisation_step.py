"""Issue 48: the time of one optimisation step, ours against Mitsuba's ``prbvolpath``.

One step as users write it: ``--views`` sensors in turn, each a gradient render
(``mi.render(scene, params, ...)`` then ``dr.backward`` of its image's L2 loss), then
Adam's step, the clamp at 0 and ``params.update()`` (which re-checks the grid and refits
its majorants). The scene: the smoke in a ball (``tools.scenes.grid``, scale 8, albedo
0.85) lit by a small light and a dim environment, the density grid the parameter; for
``prbvolpath`` both in our ``grid_medium`` and in Mitsuba's ``heterogeneous`` medium.

For each configuration (resolution, spp, max_depth): both methods warmed up (2 steps),
then ``--rounds`` rounds alternating the methods, ``--steps`` steps each; a method's time
is the median step. The steps of ours are split by Dr.Jit's kernel history into the
kernels' own time and the rest (Python tracing, launches, the optimiser and the update),
and the kernels compiled after the warm-up are counted (none expected: parameters that
change between steps are opaque).

``python3 -m benchmarks.optimisation_step [--quick]`` writes
``benchmarks/results/optimisation_step[_VARIANT].{md,json}`` (the variant suffix outside
``llvm_ad_rgb``).
"""
from __future__ import annotations

import argparse
import datetime
import itertools
import statistics
import time
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- picks libLLVM first
import drjit as dr
import mitsuba as mi

from mitsuba_plugins import output
from mitsuba_plugins.registry import default_variant

ROOT = Path(__file__).resolve().parents[1]
#: method -> (integrator, medium): prbvolpath on our grid_medium (its lookups are Python
#: callbacks there) and on Mitsuba's own heterogeneous medium with the same grid
METHODS = {"volpath_delta": ({"type": "volpath_delta"}, "grid_medium"),
           "prbvolpath": ({"type": "prbvolpath"}, "grid_medium"),
           "prbvolpath_heterogeneous": ({"type": "prbvolpath"}, "heterogeneous")}


class Problem:
    """A density fit from ``views`` sensors of ``res``^2 pixels; ``medium``: the smoke in
    ``grid_medium`` or in Mitsuba's ``heterogeneous`` (a ``gridvolume``)."""

    def __init__(self, res: int, views: int, medium: str):
        from benchmarks.inverse import ring_sensors
        from mitsuba_plugins.tools.scenes import SMOKE, grid, media_scene
        if medium == "grid_medium":
            description = grid(scale=8.0, albedo=0.85)
        else:
            description = {"type": "heterogeneous", "scale": 8.0, "albedo": 0.85,
                           "sigma_t": {"type": "gridvolume", "filename": SMOKE,
                                       "to_world": grid()["to_world"]}}
        self.scene = media_scene(description, env=0.1)
        self.params = mi.traverse(self.scene)
        self.key = next(k for k in self.params.keys() if k.startswith("ball.interior_medium")
                        and k.endswith(".data"))
        self.sensors = ring_sensors(views, res)
        reference = mi.load_dict({"type": "volpath_delta", "max_depth": 8})
        self.references = [mi.render(self.scene, sensor=s, integrator=reference, spp=64,
                                     seed=7) for s in self.sensors]
        self.start = mi.TensorXf(self.params[self.key])
        self.iteration = 0

    def optimiser(self):
        """A fresh Adam on the starting grid."""
        self.params[self.key] = mi.TensorXf(self.start)
        self.params.update()
        opt = mi.ad.Adam(lr=0.02)
        opt[self.key] = self.params[self.key]
        self.params.update(opt)
        return opt

    def step(self, integrator, opt, spp: int) -> float:
        """One step; returns its wall time (s), the device synchronised on both ends."""
        dr.sync_thread()
        t0 = time.perf_counter()
        for v, sensor in enumerate(self.sensors):
            img = mi.render(self.scene, self.params, sensor=sensor, integrator=integrator,
                            spp=spp, seed=self.iteration * len(self.sensors) + v)
            dr.backward(dr.mean(dr.square(img - self.references[v]), axis=None))
        opt.step()
        opt[self.key] = dr.maximum(opt[self.key], 0.0)
        self.params.update(opt)
        dr.eval(self.params[self.key])
        dr.sync_thread()
        self.iteration += 1
        return time.perf_counter() - t0


def measure(problems: dict, res: int, spp: int, depth: int, rounds: int, steps: int) -> dict:
    integrators = {m: mi.load_dict({**c, "max_depth": depth, "hide_emitters": True})
                   for m, (c, _) in METHODS.items()}
    opts = {m: problems[kind].optimiser() for m, (_, kind) in METHODS.items()}
    # one optimiser per method; methods on one scene: each step starts from its own grid
    grids = {m: mi.TensorXf(problems[kind].start) for m, (_, kind) in METHODS.items()}

    def run(m, n, history=False):
        problem = problems[METHODS[m][1]]
        problem.params[problem.key] = grids[m]
        problem.params.update()
        opts[m][problem.key] = problem.params[problem.key]
        problem.params.update(opts[m])
        if not history:
            out = [problem.step(integrators[m], opts[m], spp) for _ in range(n)], None
        else:
            with dr.scoped_set_flag(dr.JitFlag.KernelHistory):
                times = [problem.step(integrators[m], opts[m], spp) for _ in range(n)]
                out = times, dr.kernel_history()
        grids[m] = mi.TensorXf(problem.params[problem.key])
        return out

    for m in METHODS:
        run(m, 2)                                            # warm-up: tracing, compiling
    times = {m: [] for m in METHODS}
    kernels = {m: {"seconds": 0.0, "steps": 0, "compiled": 0, "launches": 0} for m in METHODS}
    for r in range(rounds):
        order = list(METHODS) if r % 2 == 0 else list(reversed(list(METHODS)))
        for m in order:
            t, hist = run(m, steps, history=True)
            times[m] += t
            jit = [h for h in hist if h["type"] == dr.KernelType.JIT]
            k = kernels[m]
            k["seconds"] += sum(h["execution_time"] for h in hist) / 1e3
            k["steps"] += steps
            k["compiled"] += sum(1 for h in jit if not h["cache_hit"])
            k["launches"] += len(hist)
    out = {"res": res, "spp": spp, "max_depth": depth, "methods": {}}
    for m in METHODS:
        k = kernels[m]
        median = statistics.median(times[m])
        out["methods"][m] = {"step_seconds": median, "steps": times[m],
                             "kernel_seconds_per_step": k["seconds"] / k["steps"],
                             "launches_per_step": k["launches"] / k["steps"],
                             "kernels_compiled_after_warmup": k["compiled"]}
    ours = out["methods"]["volpath_delta"]["step_seconds"]
    out["ratio"] = ours / out["methods"]["prbvolpath"]["step_seconds"]
    out["ratio_heterogeneous"] = ours / out["methods"]["prbvolpath_heterogeneous"]["step_seconds"]
    return out


def markdown(result: dict) -> str:
    cfg = result["config"]
    lines = ["# One optimisation step: volpath_delta against prbvolpath", "",
             f"Measured {result['date']} on {result['device']} ({result['variant']}) by "
             f"`python3 -m benchmarks.optimisation_step {cfg['argv']}`: {cfg['views']} views "
             "in turn per step (gradient render + backward each), Adam, clamp, "
             f"params.update(); 2 warm-up steps, then {cfg['rounds']} alternating rounds of "
             f"{cfg['steps']} steps; median step. Kernels: Dr.Jit's kernel history (their "
             "own execution time per step; the rest is tracing, launches, optimiser and "
             "update). Compiled: kernels compiled after the warm-up.", "",
             "prbvolpath runs on the same grid_medium (``prb``) and on Mitsuba's "
             "heterogeneous medium with the same grid (``prb het``).", "",
             "| res | spp | max_depth | ours (ms) | prb (ms) | prb het (ms) | ours / prb | "
             "ours / prb het | kernels: ours, prb, prb het (ms) | compiled |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        a, b, c = (r["methods"][m] for m in METHODS)
        lines.append(f"| {r['res']}^2 | {r['spp']} | {r['max_depth']} | "
                     f"{a['step_seconds'] * 1e3:.0f} | {b['step_seconds'] * 1e3:.0f} | "
                     f"{c['step_seconds'] * 1e3:.0f} | {r['ratio']:.2f} | "
                     f"{r['ratio_heterogeneous']:.2f} | " + ", ".join(
                         f"{x['kernel_seconds_per_step'] * 1e3:.0f}" for x in (a, b, c)) +
                     " | " + ", ".join(str(x["kernels_compiled_after_warmup"])
                                       for x in (a, b, c)) + " |")
    for label, k in (("prbvolpath", "ratio"), ("prbvolpath on heterogeneous",
                                                "ratio_heterogeneous")):
        ratios = sorted(r[k] for r in result["rows"])
        lines.append(f"\nRatio ours / {label}: median {statistics.median(ratios):.2f}, "
                     f"worst {ratios[-1]:.2f} (target: <= 0.8).")
    return "\n".join(lines) + "\n"


def main() -> None:
    import sys
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one configuration, 1 round")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=3)
    args = ap.parse_args()
    variant = default_variant()
    mi.set_variant(variant)
    from benchmarks.harness import device_model
    configs = [(32, 8, 8)] if args.quick else \
        list(itertools.product((32, 64), (8, 16), (8, 64)))
    rounds = 1 if args.quick else args.rounds
    result = {"date": datetime.date.today().isoformat(), "device": device_model(variant),
              "variant": variant, "rows": [],
              "config": {"views": args.views, "rounds": rounds, "steps": args.steps,
                         "argv": " ".join(sys.argv[1:])}}
    suffix = "" if variant == "llvm_ad_rgb" else f"_{variant}"
    out = ROOT / "benchmarks" / "results" / f"optimisation_step{suffix}"
    problems = {}
    for res, spp, depth in configs:
        if res not in problems:
            problems[res] = {kind: Problem(res, args.views, kind)
                             for kind in ("grid_medium", "heterogeneous")}
        row = measure(problems[res], res, spp, depth, rounds, args.steps)
        result["rows"].append(row)
        print(f"{res}^2 spp {spp} depth {depth}: ratio {row['ratio']:.2f}, "
              f"{row['ratio_heterogeneous']:.2f}", flush=True)
        if not args.quick:
            output.write_json(out.with_suffix(".json"), result, indent=1)
            output.write_text(out.with_suffix(".md"), markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
