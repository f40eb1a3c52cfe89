"""volpath_delta benchmark: speed against error next to Mitsuba's volpath.

1. Efficiency at equal time. For each scene: both integrators compiled (warm-up), the
   time per sample measured, then volpath at ``--spp`` and volpath_delta at the spp
   that takes about as long; ``--runs`` alternating renders each (different seeds).
   relMSE (docs/method.md section 1) against a reference rendered by volpath_delta at
   ``--ref-spp`` (unbiasedness against volpath is tested in tests/integrators/test_volpath_delta.py;
   the reference's own noise adds the same expected error to both sides);
   efficiency = 1 / (mean relMSE x median time). Targets (issue): homogeneous
   chromatic >= 1.3x, sparse smoke >= 3x, dense smooth heterogeneous >= 1.0x.
2. Shadow-ray transmittance estimators: efficiency of volpath_delta with each
   ``transmittance`` on the heterogeneous scenes (chooses the default), and the
   estimators alone on one segment: mean vs exp(-tau), variance, time.
3. Cost against sparsity: grids whose max/mean density rises from 1 to 100 at a fixed
   mean extinction; time per sample of both integrators relative to max/mean = 1, and
   null collisions per path. Ours are counted in our kernels
   (``instrument.counting``); Mitsuba's C++ cannot be instrumented, so its count
   is that of the same tracking with one global majorant (volpath's) and ratio-tracked
   shadow rays (volpath's), counted in our kernel with ``majorant_resolution = 1``.

Writes ``benchmarks/results/volpath_delta.{md,json}``.
"""
from __future__ import annotations

import argparse
import datetime
import json
import statistics
import tempfile
import time
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import mitsuba as mi
import drjit as dr
import numpy as np

from benchmarks.harness import alternate, device_model, timed_render
from mitsuba_plugins.registry import default_variant  # noqa: E402

VARIANT = default_variant()      # $MITSUBA_PLUGINS_VARIANT, e.g. cuda_ad_rgb on a GPU
mi.set_variant(VARIANT)
from mitsuba_plugins import instrument, output
from mitsuba_plugins.tracking import trackers, transmittance
from mitsuba_plugins.tools import stats  # noqa: E402  (needs a variant)

ROOT = Path(__file__).resolve().parents[1]
TARGETS = {"homogeneous_chromatic": 1.3, "sparse_smoke": 3.0, "dense_smooth": 1.0}
MAX_DEPTH = 16


# -- scenes -------------------------------------------------------------------------------
def _base(res: int, medium: dict) -> dict:
    return {
        "type": "scene",
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 0.15}},
        "light": {"type": "sphere", "center": [2.0, 2.5, 1.5], "radius": 0.3,
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 25.0}}},
        "floor": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([0, -1.0, 0]).rotate(
                      [1, 0, 0], -90).scale(3),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at([0.2, 0.9, 3.2], [0, 0, 0],
                                                              [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 16}},
        "box": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium},
    }


def smooth_field(n: int = 48, seed: int = 3) -> np.ndarray:
    """A smooth positive field on n^3 (sum of a few low-frequency sinusoids), mean 1."""
    rng = np.random.default_rng(seed)
    z, y, x = np.meshgrid(*(np.linspace(0, 1, n),) * 3, indexing="ij")
    f = np.zeros((n, n, n))
    for _ in range(6):
        k = rng.uniform(1.0, 3.0, 3) * 2 * np.pi
        f += np.sin(k[0] * x + rng.uniform(0, 6)) * np.sin(k[1] * y + rng.uniform(0, 6)) \
            * np.sin(k[2] * z + rng.uniform(0, 6))
    f = (f - f.min()) / (f.max() - f.min())
    return (f / f.mean()).astype(np.float32)


def contrast_field(ratio: float, n: int = 48) -> np.ndarray:
    """The smooth field raised to the power that gives max/mean = ``ratio`` (mean 1)."""
    base = smooth_field(n)
    if ratio <= 1.0:
        return np.ones_like(base)
    lo, hi = 0.0, 64.0
    for _ in range(60):
        p = 0.5 * (lo + hi)
        f = base ** p
        lo, hi = (p, hi) if f.max() / f.mean() < ratio else (lo, p)
    f = base ** (0.5 * (lo + hi))
    return (f / f.mean()).astype(np.float32)


def grid_medium(path: str, scale: float, **kw) -> dict:
    medium = {"type": "grid_medium", "filename": path, "scale": scale, "albedo": 0.9,
              "to_world": mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2),
              "phase": {"type": "hg", "g": 0.4}}
    medium.update(kw)
    return medium


def build_scenes(res: int, tmp: Path) -> dict:
    dense = tmp / "dense.npy"
    np.save(dense, smooth_field())
    chroma = {"type": "homogeneous", "albedo": 0.9, "scale": 6.0,
              "sigma_t": {"type": "rgb", "value": [0.08, 0.35, 1.0]},
              "phase": {"type": "hg", "g": 0.3}}
    sparse = mi.load_file(str(ROOT / "scenes" / "sparse.xml"), res=str(res),
                          max_depth=str(MAX_DEPTH))
    return {
        "homogeneous_chromatic": mi.load_dict(_base(res, chroma)),
        "sparse_smoke": sparse,
        "dense_smooth": mi.load_dict(_base(res, grid_medium(str(dense), 5.0))),
    }


# -- measurements ---------------------------------------------------------------------------
def equal_time(scene, ours: dict, builtin: dict, spp: int, runs: int, reference) -> dict:
    integ = {"ours": mi.load_dict(ours), "builtin": mi.load_dict(builtin)}
    per_spp = {}
    for k in integ:                                   # compile, then time one render
        timed_render(scene, integ[k], spp, seed=10 ** 6)
        per_spp[k] = timed_render(scene, integ[k], spp, seed=10 ** 6 + 1)[0] / spp
    n = {"builtin": spp, "ours": max(4, int(round(spp * per_spp["builtin"] / per_spp["ours"])))}
    if n["ours"] != spp:
        timed_render(scene, integ["ours"], n["ours"], seed=10 ** 6 + 2)  # new spp: compile
    times, images = alternate(integ, runs, lambda k, run: timed_render(scene, integ[k], n[k], run))
    for k in integ:
        assert all(np.isfinite(img).all() for img in images[k]), f"{k}: non-finite pixels"
    errors = {k: [stats.rel_mse(img, reference) for img in images[k]] for k in integ}
    out = {}
    for k in integ:
        t, e = statistics.median(times[k]), float(np.mean(errors[k]))
        out[k] = {"spp": n[k], "median_s": t, "times_s": times[k], "rel_mse": e,
                  "efficiency": stats.efficiency(e, t)}
    out["time_per_spp_ratio"] = per_spp["ours"] / per_spp["builtin"]
    out["rel_mse_ratio_equal_time"] = out["builtin"]["rel_mse"] / out["ours"]["rel_mse"]
    out["efficiency_ratio"] = out["ours"]["efficiency"] / out["builtin"]["efficiency"]
    return out


def reference_image(scene, spp: int) -> np.ndarray:
    integ = mi.load_dict({"type": "volpath_delta", "max_depth": MAX_DEPTH})
    chunk = min(spp, 512)
    images = [np.array(mi.render(scene, integrator=integ, spp=chunk, seed=7 * 10 ** 6 + i))
              for i in range(max(1, spp // chunk))]
    return np.mean(images, axis=0)


def estimators_alone(path: str, n: int = 1 << 20) -> dict:
    """Each transmittance estimator on one segment through a grid: mean, exp(-tau),
    variance and time per 2^20 estimates (compiled first)."""
    medium = mi.load_dict(grid_medium(path, 5.0))
    tracker = trackers.tracker_for(medium)
    o, d = mi.Point3f(-1.2, -0.3, -0.9), dr.normalize(mi.Vector3f(1.0, 0.4, 0.6))
    ray = mi.Ray3f(dr.zeros(mi.Point3f, n) + o, dr.zeros(mi.Vector3f, n) + d)
    steps, length = 100000, 4.0
    t = (dr.arange(mi.Float, steps) + 0.5) * (length / steps)
    mei = dr.zeros(mi.MediumInteraction3f, steps)
    mei.p = o + d * t
    p = np.array(mei.p)
    inside = np.all((p >= -1) & (p <= 1), axis=0)
    tau = float((np.array(medium.eval_sigma_t(mei))[0] * inside).sum() * length / steps)
    out = {"exp_minus_tau": float(np.exp(-tau)), "tau": tau}
    for method in transmittance.TRANSMITTANCE_ESTIMATORS:
        times = []
        for seed in range(4):
            sampler = mi.load_dict({"type": "independent"})
            sampler.seed(seed, n)
            t0 = time.perf_counter()
            T = transmittance.TRANSMITTANCE_ESTIMATORS[method].transmittance(
                tracker, ray, mi.Float(length), sampler, mi.Bool(True))
            dr.eval(T)
            dr.sync_thread()
            times.append(time.perf_counter() - t0)
        values = np.array(T)[0]
        out[method] = {"mean": float(values.mean()), "variance": float(values.var()),
                       "se": float(values.std() / np.sqrt(n)),
                       "seconds": statistics.median(times[1:])}
    return out


def sparsity_series(res: int, spp: int, runs: int, tmp: Path, ratios) -> list:
    rows = []
    for ratio in ratios:
        path = tmp / f"contrast_{ratio:g}.npy"
        field = contrast_field(ratio)
        np.save(path, field)
        row = {"target_max_over_mean": ratio,
               "max_over_mean": float(field.max() / field.mean())}
        scene = mi.load_dict(_base(res, grid_medium(str(path), 2.0)))
        integ = {"ours": mi.load_dict({"type": "volpath_delta", "max_depth": MAX_DEPTH,
                                       "transmittance": "ratio"}),
                 "builtin": mi.load_dict({"type": "volpath", "max_depth": MAX_DEPTH})}
        for k in integ:
            timed_render(scene, integ[k], spp, seed=10 ** 6)
        times, _ = alternate(integ, runs,
                             lambda k, run: timed_render(scene, integ[k], spp, run))
        for k in integ:
            row[f"{k}_s_per_sample"] = statistics.median(times[k]) / (spp * res * res)
        paths = spp * res * res
        for label, cells in (("ours", None), ("builtin_estimate", 1)):
            # volpath's stand-in: one global majorant and no refinement of hot segments
            kw = {} if cells is None else {"majorant_resolution": cells}  # None: as timed
            with instrument.refinement(float("inf") if label == "builtin_estimate" else
                                       instrument.REFINE_OPTICAL_DEPTH):
                counted = mi.load_dict(_base(res, grid_medium(str(path), 2.0, **kw)))
            with instrument.counting() as counts:
                mi.render(counted, integrator=mi.load_dict(
                    {"type": "volpath_delta", "max_depth": MAX_DEPTH, "transmittance": "ratio"}),
                    spp=spp, seed=99)
                row[f"{label}_null_per_path"] = (counts["flight_null"]
                                                 + counts["shadow_tentative"]) / paths
                row[f"{label}_null_free_flight_per_path"] = counts["flight_null"] / paths
        rows.append(row)
    base = rows[0]
    for row in rows:
        for k in ("ours", "builtin"):
            row[f"{k}_cost_growth"] = row[f"{k}_s_per_sample"] / base[f"{k}_s_per_sample"]
    return rows


# -- report -------------------------------------------------------------------------------------
def markdown(result: dict) -> str:
    cfg = result["config"]
    lines = [
        "# volpath_delta vs Mitsuba's volpath", "",
        f"Measured {result['date']} on {result['cpu']} ({VARIANT}, Mitsuba {mi.__version__}) by "
        f"`python3 -m benchmarks.volpath_delta` (res {cfg['res']}, volpath {cfg['spp']} spp, "
        f"{cfg['runs']} alternating runs, median time; reference: volpath_delta "
        f"{cfg['ref_spp']} spp; max_depth {MAX_DEPTH}).", "",
        "## Efficiency at equal time (target per scene)", "",
        "| scene | volpath spp | ours spp | time/spp ratio | relMSE volpath | relMSE ours | "
        "relMSE ratio (equal time) | efficiency ratio | target | met |",
        "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in result["efficiency"].items():
        target = TARGETS[name]
        lines.append(
            f"| {name} | {r['builtin']['spp']} | {r['ours']['spp']} | "
            f"{r['time_per_spp_ratio']:.3f} | {r['builtin']['rel_mse']:.3e} | "
            f"{r['ours']['rel_mse']:.3e} | {r['rel_mse_ratio_equal_time']:.2f} | "
            f"**{r['efficiency_ratio']:.2f}x** | >= {target}x | "
            f"{'yes' if r['efficiency_ratio'] >= target else 'NO'} |")
    lines += ["", "## Shadow-ray transmittance estimators in the integrator (efficiency vs volpath)",
              "", "| scene | " + " | ".join(transmittance.TRANSMITTANCE_ESTIMATORS) + " |",
              "|---|" + "---|" * len(transmittance.TRANSMITTANCE_ESTIMATORS)]
    for name, per in result["estimators_in_integrator"].items():
        lines.append(f"| {name} | " + " | ".join(f"{per[m]['efficiency_ratio']:.2f}x"
                                              for m in transmittance.TRANSMITTANCE_ESTIMATORS) + " |")
    lines += ["", "## Transmittance estimators alone (one segment, 2^20 estimates)", ""]
    for name, r in result["estimators_alone"].items():
        lines += [f"{name}: tau = {r['tau']:.3f}, exp(-tau) = {r['exp_minus_tau']:.5f}", "",
                  "| estimator | mean +- se | variance | time (s) | variance x time |",
                  "|---|---|---|---|---|"]
        for m in transmittance.TRANSMITTANCE_ESTIMATORS:
            e = r[m]
            lines.append(f"| {m} | {e['mean']:.5f} +- {e['se']:.5f} | {e['variance']:.3e} | "
                         f"{e['seconds']:.4f} | {e['variance'] * e['seconds']:.3e} |")
        lines.append("")
    lines += ["## Cost against sparsity (fixed mean extinction; target: ours grows <= 1.5x)", "",
              *([f"Section re-run {result['sparsity_date']} (`--only sparsity`).", ""]
                if "sparsity_date" in result else []),
              "Collisions per path: null collisions in free flight + tentative collisions on "
              "shadow rays (every one costs a density lookup); volpath's are estimated (see "
              "the module docstring).", "",
              "| max/mean | ours s/sample | ours growth | volpath s/sample | volpath growth | "
              "ours: null (free flight) / all per path | volpath (est.): null (free flight) "
              "/ all per path |",
              "|---|---|---|---|---|---|---|"]
    for r in result["sparsity"]:
        lines.append(
            f"| {r['max_over_mean']:.1f} | {r['ours_s_per_sample']:.3e} | "
            f"{r['ours_cost_growth']:.2f}x | {r['builtin_s_per_sample']:.3e} | "
            f"{r['builtin_cost_growth']:.2f}x | {r['ours_null_free_flight_per_path']:.2f} / "
            f"{r['ours_null_per_path']:.2f} | {r['builtin_estimate_null_free_flight_per_path']:.2f}"
            f" / {r['builtin_estimate_null_per_path']:.2f} |")
    growth = max(r["ours_cost_growth"] for r in result["sparsity"])
    lines += ["", f"Largest growth of our time per sample: {growth:.2f}x "
              f"({'meets' if growth <= 1.5 else 'MISSES'} the 1.5x target).", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--ref-spp", type=int, default=8192)
    ap.add_argument("--ratios", default="1,3,10,30,100")
    ap.add_argument("--only", choices=("sparsity",),
                    help="re-run one section and merge it into the committed results")
    suffix = "" if VARIANT == "llvm_ad_rgb" else f"_{VARIANT}"
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / f"volpath_delta{suffix}"))
    args = ap.parse_args()
    out = Path(args.out)
    if args.only:
        result = json.loads(out.with_suffix(".json").read_text())
        with tempfile.TemporaryDirectory() as tmpdir:
            result["sparsity"] = sparsity_series(args.res, args.spp // 2, args.runs, Path(tmpdir),
                                                 [float(r) for r in args.ratios.split(",")])
        result["sparsity_date"] = datetime.date.today().isoformat()
        output.write_json(out.with_suffix(".json"), result, indent=1)
        output.write_text(out.with_suffix(".md"), markdown(result))
        print(markdown(result))
        return
    result = {"date": datetime.date.today().isoformat(), "cpu": device_model(VARIANT),
              "variant": VARIANT,
              "config": {"res": args.res, "spp": args.spp, "runs": args.runs,
                         "ref_spp": args.ref_spp},
              "efficiency": {}, "estimators_in_integrator": {}}
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        scenes = build_scenes(args.res, tmp)
        builtin = {"type": "volpath", "max_depth": MAX_DEPTH}
        for name, scene in scenes.items():
            ref = reference_image(scene, args.ref_spp)
            result["efficiency"][name] = equal_time(
                scene, {"type": "volpath_delta", "max_depth": MAX_DEPTH}, builtin, args.spp,
                args.runs, ref)
            print(name, f"{result['efficiency'][name]['efficiency_ratio']:.2f}x", flush=True)
            if name != "homogeneous_chromatic":
                result["estimators_in_integrator"][name] = {
                    m: equal_time(scene, {"type": "volpath_delta", "max_depth": MAX_DEPTH,
                                          "transmittance": m}, builtin, args.spp, args.runs, ref)
                    for m in transmittance.TRANSMITTANCE_ESTIMATORS}
        np.save(tmp / "sparse_like.npy", contrast_field(50.0))
        np.save(tmp / "dense.npy", smooth_field())
        result["estimators_alone"] = {
            "dense_smooth": estimators_alone(str(tmp / "dense.npy")),
            "sparse (max/mean 50)": estimators_alone(str(tmp / "sparse_like.npy"))}
        result["sparsity"] = sparsity_series(args.res, args.spp // 2, args.runs, tmp,
                                             [float(r) for r in args.ratios.split(",")])
    out.parent.mkdir(parents=True, exist_ok=True)
    output.write_json(out.with_suffix(".json"), result, indent=1)
    output.write_text(out.with_suffix(".md"), markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
