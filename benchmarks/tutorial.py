"""Issue 48, part 5: Mitsuba's ``volume_optimization`` tutorial, ``prbvolpath`` against ours.

The tutorial (mitsuba-tutorials, ``inverse_rendering/volume_optimization.ipynb``) as
written: a ``heterogeneous`` medium (``sigma_t`` a ``gridvolume`` read from the
tutorial's ``volume.vol`` in its scenes folder, ``scale`` 40, the default albedo 0.75)
in a cube with a ``null`` BSDF under a ``constant`` emitter; 5 sensors of 64^2 on a half
circle; references at 512 spp (``prbvolpath``'s primal); a 16^3 grid at 0.002 optimised
with ``mi.ad.Adam(lr=0.02)``, one Adam step per view (the tutorial's loop), the clamp to
[1e-6, 1]; 20 iterations at 8 spp, then ``dr.resample`` to 64^3 and 20 iterations at 64
spp. The tutorial's printed losses (the sum over views of each view's training loss in
the last iteration) are 0.0446 and 0.0176.

Methods, on the same scene: ``prbvolpath`` (the tutorial) and ``volpath_delta`` (the
same scene with the integrator swapped). ``prbvolpath`` runs the schedule; ours runs the
same schedule and then goes on at 64^3 until it has used prbvolpath's wall time, so both
end at equal time. Timed: the optimisation steps only (every timed block ends with
``dr.sync_thread()``). Every 2 iterations (untimed): the loss, an unbiased estimate of the
squared error of the expected image (mean over views of (A - R)(B - R), A and B two
independent 32-spp ``volpath_delta`` primal renders with fixed seeds, R the reference), and the
relative L2 error of the grid against the tutorial's grid resampled at the optimised
grid's voxel centres (the reference cube is rotated by -90 degrees about x).

The volume file is not ours to ship (the tutorials repository states no licence): pass
``--volume PATH`` (default: ``tutorial_volume.vol`` beside our scenes' grids,
git-ignored); its SHA-256 is recorded.

``python3 -m benchmarks.tutorial [--seeds 0 1] [--quick] [--lr-fine LR]`` writes
``benchmarks/results/tutorial.{md,json}`` and ``docs/results/tutorial.png`` (with
``--lr-fine``, the learning rate of both methods after the upsampling:
``tutorial_lr<LR>.*``; with ``--lr-prb``, prbvolpath's learning rate in both phases,
ours keeping the tutorial's: ``tutorial_prblr<LR>.*``); ``--profile`` times one
gradient render per method.
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import time
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- picks libLLVM first
import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins.registry import default_variant

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
PLOTS = ROOT / "docs" / "results"
DEFAULT_VOLUME = ROOT / "scenes" / "data" / "tutorial_volume.vol"
KEY = "object.interior_medium.sigma_t.data"
METHODS = ("prbvolpath", "volpath_delta")
#: the tutorial's schedule: (grid resolution, iterations, spp) per phase
PHASES = ((16, 20, 8), (64, 20, 64))
VIEWS, RES, REF_SPP, LR = 5, 64, 512, 0.02
EVALUATE_EVERY = 2


def sensors():
    T = mi.ScalarTransform4f
    out = []
    for i in range(VIEWS):
        angle = 180.0 / VIEWS * i - 90.0
        to_world = T().rotate([0, 1, 0], angle) @ T().look_at(target=[0, 0, 0],
                                                              origin=[0, 0, 4], up=[0, 1, 0])
        out.append(mi.load_dict({"type": "perspective", "fov": 45, "to_world": to_world,
                                 "film": {"type": "hdrfilm", "width": RES, "height": RES,
                                          "filter": {"type": "tent"}}}))
    return out


def scene_dict(sigma_t: dict, integrator: str) -> dict:
    return {"type": "scene", "integrator": {"type": integrator},
            "object": {"type": "cube", "bsdf": {"type": "null"},
                       "interior": {"type": "heterogeneous", "sigma_t": sigma_t,
                                    "scale": 40.0}},
            "emitter": {"type": "constant"}}


def ref_to_world():
    """The tutorial's placement of its grid."""
    return mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(2).translate(-0.5)


def opt_to_world():
    """The tutorial's placement of the optimised grid."""
    return mi.ScalarTransform4f().translate(-1).scale(2.0)


def reference_grid(volume: Path, res: int) -> np.ndarray:
    """The tutorial's grid seen at the voxel centres of a ``res``^3 grid placed as the
    optimised one (:func:`opt_to_world`): trilinear lookups of its data (a gridvolume's)."""
    from mitsuba_plugins.grids import gridio
    data = gridio.read_grid(str(volume))[0]
    tex = mi.Texture3f(mi.TensorXf(data.astype(np.float32)))
    c = (np.arange(res) + 0.5) / res
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    world = mi.Transform4f(opt_to_world()) @ mi.Point3f(*(mi.Float(a.ravel())
                                                           for a in (x, y, z)))
    uvw = mi.Transform4f(ref_to_world().inverse()) @ world
    values = np.array(tex.eval(mi.Point3f(uvw))[0])
    return values.reshape(res, res, res, 1)


class Run:
    """One optimisation (``method``, render seeds offset by ``seed``)."""

    def __init__(self, method, views, references, volume, seed, lr=LR):
        self.views, self.references, self.seed = views, references, seed
        start = dr.full(mi.TensorXf, 0.002, (PHASES[0][0],) * 3 + (1,))
        self.scene = mi.load_dict(scene_dict({"type": "gridvolume",
                                              "grid": mi.VolumeGrid(start),
                                              "to_world": opt_to_world()}, method))
        # ours' primal: unbiased (tests/integrators), the same for both methods, and 16x
        # faster than volpath on this scene (its one global majorant)
        self.evaluator = mi.load_dict({"type": "volpath_delta"})
        self.params = mi.traverse(self.scene)
        self.opt = mi.ad.Adam(lr=lr)
        self.opt[KEY] = self.params[KEY]
        self.params.update(self.opt)
        self.truth = {r: reference_grid(volume, r) for r, _, _ in PHASES}
        self.spent, self.iteration, self.history, self.training_loss = 0.0, 0, [], []

    def evaluate(self):
        loss = []
        for v, s in enumerate(self.views):
            a, b = (mi.render(self.scene, sensor=s, integrator=self.evaluator, spp=32,
                              seed=1000 * k + v) - self.references[v] for k in (1, 2))
            loss.append(float(dr.mean(a * b, axis=None).array[0]))
        grid = np.array(self.params[KEY])
        truth = self.truth[grid.shape[0]]
        error = float(np.linalg.norm(grid - truth) / np.linalg.norm(truth))
        self.history.append({"seconds": self.spent, "iteration": self.iteration,
                             "resolution": grid.shape[0], "loss": float(np.mean(loss)),
                             "error": error})

    def iterate(self, spp):
        """One tutorial iteration: a gradient render, backward and Adam step per view."""
        dr.sync_thread()
        t0 = time.perf_counter()
        total = mi.Float(0.0)
        for v, sensor in enumerate(self.views):
            img = mi.render(self.scene, self.params, sensor=sensor, spp=spp,
                            seed=100_000 * self.seed + self.iteration)
            loss = dr.mean(dr.square(img - self.references[v]), axis=None)
            dr.backward(loss)
            self.opt.step()
            self.opt[KEY] = dr.clip(self.opt[KEY], 1e-6, 1.0)
            self.params.update(self.opt)
            total += dr.detach(loss)
        dr.eval(self.params[KEY], total)
        dr.sync_thread()
        self.spent += time.perf_counter() - t0
        self.iteration += 1
        self.training_loss.append(float(total.array[0]))
        if self.iteration % EVALUATE_EVERY == 0:
            self.evaluate()

    def upsample(self, res):
        dr.sync_thread()
        t0 = time.perf_counter()
        self.opt[KEY] = dr.resample(self.opt[KEY], shape=(res,) * 3 + (1,), filter="linear")
        self.params.update(self.opt)
        dr.sync_thread()
        self.spent += time.perf_counter() - t0


def optimise(method, views, references, volume, seed, budget=None, lr_fine=LR,
             lr=LR) -> dict:
    """The tutorial's schedule at learning rate ``lr``, ``lr_fine`` after the upsampling;
    with ``budget`` (seconds), the last phase goes on until it is spent."""
    run = Run(method, views, references, volume, seed, lr)
    run.evaluate()
    phase_loss = []
    for p, (res, iterations, spp) in enumerate(PHASES):
        if p:
            run.upsample(res)
            run.opt.lr = lr_fine
        for _ in range(iterations):
            run.iterate(spp)
        phase_loss.append(run.training_loss[-1])
    schedule_seconds = run.spent
    while budget is not None and run.spent < budget:
        run.iterate(PHASES[-1][2])
    if run.history[-1]["iteration"] != run.iteration:
        run.evaluate()
    print(f"{method} seed {seed}: {run.iteration} iterations in {run.spent:.0f} s "
          f"(schedule {schedule_seconds:.0f} s), tutorial losses "
          f"{phase_loss[0]:.4f} {phase_loss[1]:.4f}, final loss {run.history[-1]['loss']:.3e}"
          f", error {run.history[-1]['error']:.3f}", flush=True)
    return {"iterations": run.iteration, "seconds": run.spent,
            "schedule_seconds": schedule_seconds, "tutorial_losses": phase_loss,
            "history": run.history}


def first_time(history, key, value) -> float:
    for h in history:
        if h[key] <= value:
            return h["seconds"]
    return float("inf")


def markdown(result, name="tutorial") -> str:
    lines = ["# Mitsuba's volume_optimization tutorial: prbvolpath against volpath_delta", "",
             f"Measured {result['date']} on {result['device']} ({result['variant']}) by "
             f"`python3 -m benchmarks.tutorial {result['argv']}` (benchmarks/tutorial.py "
             "says how). Volume file SHA-256 "
             f"`{result['volume_sha256'][:16]}...`.", "",
             "prbvolpath runs the tutorial's schedule (20 iterations at 16^3 and 8 spp, "
             "20 at 64^3 and 64 spp, one Adam step per view); ours runs the same schedule, "
             "then goes on at 64^3 until it has used prbvolpath's time. 'Tutorial losses': "
             "the tutorial's own printout (sum over views of the training losses of the "
             "last iteration of each phase; the notebook shows 0.0446 and 0.0176). Loss: "
             "unbiased estimate of the squared error of the expected image; error: relative "
             "L2 error of the grid.", "",
             "| seed | method | schedule time (s) | tutorial losses | iterations at equal "
             "time | final loss | final grid error | reaches prbvolpath's final loss / "
             "error after |",
             "|---|---|---|---|---|---|---|---|"]
    for r in result["seeds"]:
        prb = r["prbvolpath"]
        for m in METHODS:
            x = r[m]
            h = x["history"][-1]
            if m == "prbvolpath":
                reach = "-"
            else:
                tl = first_time(x["history"], "loss", prb["history"][-1]["loss"])
                te = first_time(x["history"], "error", prb["history"][-1]["error"])
                reach = " / ".join("never" if not np.isfinite(t) else
                                   f"{t / prb['seconds']:.2f}x" for t in (tl, te))
            lines.append(f"| {r['seed']} | {m} | {x['schedule_seconds']:.0f} | "
                         f"{x['tutorial_losses'][0]:.4f}, {x['tutorial_losses'][1]:.4f} | "
                         f"{x['iterations']} | {h['loss']:.3e} | {h['error']:.3f} | "
                         f"{reach} |")
    lines += ["", "Reaching times are fractions of prbvolpath's wall time (target <= 0.5x, "
              "issue 48).", "", "![loss and grid error over time](../../docs/results/"
              f"{name}.png)", ""]
    return "\n".join(lines)


def plot(result, name="tutorial") -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for m, colour in zip(METHODS, ("C1", "C0")):
        for i, r in enumerate(result["seeds"]):
            h = r[m]["history"]
            t = [x["seconds"] for x in h]
            axes[0].semilogy(t, [max(x["loss"], 1e-7) for x in h], colour,
                             label=m if i == 0 else None, alpha=0.8)
            axes[1].plot(t, [x["error"] for x in h], colour, label=m if i == 0 else None,
                         alpha=0.8)
    axes[0].set(xlabel="seconds of optimisation", ylabel="loss (unbiased estimate)",
                title=f"volume_optimization tutorial ({name})")
    axes[1].set(xlabel="seconds of optimisation", ylabel="relative L2 error of the grid")
    axes[0].legend()
    fig.tight_layout()
    PLOTS.mkdir(parents=True, exist_ok=True)
    fig.savefig(PLOTS / f"{name}.png", dpi=100)


def profile(volume: Path, runs: int = 3) -> None:
    """One view's gradient render (64 spp, backward of its L2 loss) and primal render
    with the tutorial's grid resampled to 64^3 in the optimised placement, both methods
    alternating after a warm-up; prints the median seconds."""
    views = sensors()
    grid = mi.TensorXf(reference_grid(volume, 64).astype(np.float32))
    scene = mi.load_dict(scene_dict({"type": "gridvolume", "grid": mi.VolumeGrid(grid),
                                     "to_world": opt_to_world()}, "volpath"))
    params = mi.traverse(scene)
    target = mi.render(scene, sensor=views[0], spp=4)
    integrators = {m: mi.load_dict({"type": m}) for m in METHODS}
    dr.enable_grad(params[KEY])
    params.update()

    def timed(m, seed, gradient):
        dr.sync_thread()
        t0 = time.perf_counter()
        if gradient:
            img = mi.render(scene, params, sensor=views[0], integrator=integrators[m],
                            spp=64, seed=seed)
            dr.backward(dr.mean(dr.square(img - target), axis=None))
            dr.eval(dr.grad(params[KEY]))
        else:
            with dr.suspend_grad():
                dr.eval(mi.render(scene, sensor=views[0], integrator=integrators[m], spp=64,
                                  seed=seed))
        dr.sync_thread()
        return time.perf_counter() - t0
    times = {(m, g): [] for m in METHODS for g in (True, False)}
    for run in range(runs + 1):
        for m in METHODS if run % 2 == 0 else METHODS[::-1]:
            for g in (True, False):
                t = timed(m, run, g)
                if run:                       # run 0: the warm-up
                    times[(m, g)].append(t)
    for m in METHODS:
        print(f"{m}: gradient render {np.median(times[(m, True)]):.3f} s, primal "
              f"{np.median(times[(m, False)]):.3f} s (64^2, 64 spp, median of {runs})")


def main() -> None:
    import sys
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--volume", type=Path, default=DEFAULT_VOLUME)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--quick", action="store_true", help="2 + 2 iterations, 1 seed")
    ap.add_argument("--profile", action="store_true",
                    help="time one gradient render per method at the tutorial's grid")
    ap.add_argument("--lr-fine", type=float, default=LR,
                    help="Adam's learning rate after the upsampling, both methods (the "
                         "tutorial's: 0.02); another writes tutorial_lr<value>.*")
    ap.add_argument("--lr-prb", type=float,
                    help="prbvolpath's learning rate in both phases (ours keeps the "
                         "tutorial's); writes tutorial_prblr<value>.*")
    args = ap.parse_args()
    if not args.volume.exists():
        raise SystemExit(f"--volume: {args.volume} does not exist (the tutorial's "
                         "volume.vol in the scenes folder of mitsuba-renderer/mitsuba-tutorials)")
    global PHASES
    if args.quick:
        PHASES = tuple((r, 2, s) for r, _, s in PHASES)
        args.seeds = args.seeds[:1]
    variant = default_variant()
    mi.set_variant(variant)
    if args.profile:
        profile(args.volume)
        return
    from benchmarks.harness import device_model
    views = sensors()
    ref_scene = mi.load_dict(scene_dict({"type": "gridvolume", "filename": str(args.volume),
                                         "to_world": ref_to_world()}, "prbvolpath"))
    references = [mi.render(ref_scene, sensor=s, spp=REF_SPP, seed=7) for s in views]
    result = {"date": datetime.date.today().isoformat(), "device": device_model(variant),
              "variant": variant, "argv": " ".join(sys.argv[1:]),
              "volume_sha256": hashlib.sha256(args.volume.read_bytes()).hexdigest(),
              "seeds": []}
    for seed in args.seeds:
        prb = optimise("prbvolpath", views, references, args.volume, seed,
                       lr_fine=args.lr_prb or args.lr_fine, lr=args.lr_prb or LR)
        ours = optimise("volpath_delta", views, references, args.volume, seed,
                        budget=prb["seconds"], lr_fine=args.lr_fine)
        result["seeds"].append({"seed": seed, "prbvolpath": prb, "volpath_delta": ours})
    if args.quick:
        print(markdown(result))
        return
    name = "tutorial" if args.lr_fine == LR else f"tutorial_lr{args.lr_fine:g}"
    if args.lr_prb:
        name = f"tutorial_prblr{args.lr_prb:g}"
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(result, indent=1))
    (RESULTS / f"{name}.md").write_text(markdown(result, name))
    plot(result, name)
    print(markdown(result, name))


if __name__ == "__main__":
    main()
