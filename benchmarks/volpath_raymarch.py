"""volpath_raymarch benchmark: its bias per step size, and error against time next to
volpath_delta and Mitsuba's volpath.

1. Bias per step (scenes smoke, chromatic, sparse with ``mode = multi``, max_depth 16;
   the smoke with ``mode = single`` at max_depth 2). On these scenes the march's bias
   is far below the noise of any independent reference we can afford (measured: at a
   step of 0.25, an eighth of the box, the smoke's squared relative bias is ~1e-6,
   while a 4096-spp volpath reference's own relMSE is ~4e-5). So each step's bias is
   measured *paired*: against a fine march (step 1/64; 1/32 for ``single``, whose cost
   grows with the square of the step count) rendered with the same seeds (common random
   numbers; ``--bias-passes`` x ``--bias-spp`` at ``--bias-res``^2, ``single`` at an
   eighth of the spp), whose difference has far less variance. A small image with many
   samples per pixel resolves a smaller bias for the same work. ``bias2 = mean(((a - f)^2 - var(a - f)) / (f^2 + eps))`` with
   ``noise`` the subtracted variance (bias2 below ~noise is not resolved), and the
   image-mean bias ``mean(a) / mean(f) - 1``. The fine march itself is compared with
   the independent unbiased reference (Mitsuba's volpath at ``--bias-ref-spp`` in 16
   passes; on the chromatic scene volpath_delta, since volpath is biased there,
   docs/validation.md) the same way, unpaired. The order is the slope of log |image-mean
   bias| against log(step) over the steps where that bias exceeds 3 standard errors.
2. Error against time (smoke and sparse): each integrator renders passes of
   ``--curve-spp`` until ``--budget`` seconds are spent (compiled first); after each
   pass the relative MSE of the running mean against a volpath reference at ``--res``^2
   and ``--ref-spp`` (16 passes), minus the reference's own variance, is recorded with the accumulated time. One log-log plot
   per scene; a table gives the time each method takes to reach given errors.

Writes ``benchmarks/results/volpath_raymarch.{md,json}`` and ``volpath_raymarch_<scene>.png``.
"""
from __future__ import annotations

import argparse
import datetime
import time
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import mitsuba as mi
import numpy as np

from benchmarks.harness import cpu_model, timed_render

mi.set_variant("llvm_ad_rgb")
from mitsuba_plugins import output
from mitsuba_plugins.tools import stats  # noqa: E402  (needs a variant)

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
MAX_DEPTH = 16
STEPS = (1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125)
FINE_STEP = 1 / 64
#: ``single``: the fine step and the steps studied (each cell marches a shadow ray)
SINGLE_FINE_STEP = 1 / 32
SINGLE_STEPS = (1.0, 0.5, 0.25, 0.125, 0.0625)
CURVE_STEPS = (0.5, 0.125, 0.03125)
TARGET_ERRORS = (1e-2, 1e-3, 3e-4, 1e-4)


def load(name: str, res: int, max_depth: int = MAX_DEPTH):
    return mi.load_file(str(ROOT / "scenes" / f"{name}.xml"), res=str(res),
                        max_depth=str(max_depth))


class Passes:
    """Independent passes: their images, mean, the variance of the mean, the time."""

    def __init__(self, scene, integrator: dict, passes: int, spp: int, seed: int):
        integ = mi.load_dict(integrator)
        timed_render(scene, integ, spp, seed=10 ** 7 + seed)             # compile
        images, self.seconds = [], 0.0
        for k in range(passes):
            t, img = timed_render(scene, integ, spp, seed=seed + k)
            assert np.isfinite(img).all(), f"{integrator}: non-finite pixels"
            images.append(img)
            self.seconds += t
        self.images = np.array(images, dtype=np.float64)
        self.mean = self.images.mean(axis=0)
        self.var = self.images.var(axis=0, ddof=1) / passes


def _weights(ref: np.ndarray) -> np.ndarray:
    return 1.0 / (ref ** 2 + stats.REL_MSE_EPS)


def _summary(diff_mean, diff_var, image_diffs, base: Passes) -> dict:
    """Squared relative bias (noise subtracted), the noise, and the image-mean bias."""
    w = _weights(base.mean)
    level = base.images.mean()
    return {"bias2": float(np.mean((diff_mean ** 2 - diff_var) * w)),
            "noise": float(np.mean(diff_var * w)),
            "image_mean_bias": float(np.mean(image_diffs) / level),
            "image_mean_bias_se": float(np.sqrt(np.var(image_diffs, ddof=1) / len(image_diffs))
                                        / level)}


def paired_bias(est: Passes, fine: Passes) -> dict:
    """``est`` against ``fine`` rendered with the same seeds (differences per pass)."""
    d = est.images - fine.images
    return {**_summary(d.mean(axis=0), d.var(axis=0, ddof=1) / len(d), d.mean(axis=(1, 2, 3)),
                       fine), "seconds": est.seconds}


def independent_bias(est: Passes, ref: Passes) -> dict:
    """``est`` against an independent reference (variances add)."""
    a, r = est.images.mean(axis=(1, 2, 3)), ref.images.mean(axis=(1, 2, 3))
    out = _summary(est.mean - ref.mean, est.var + ref.var, a - r.mean(), ref)
    out["image_mean_bias_se"] = float(np.sqrt(a.var(ddof=1) / len(a) + r.var(ddof=1) / len(r))
                                      / ref.images.mean())
    return out


def order_of(steps, rows) -> float | None:
    keep = [(s, abs(r["image_mean_bias"])) for s, r in zip(steps, rows)
            if abs(r["image_mean_bias"]) > 3 * r["image_mean_bias_se"]]
    if len(keep) < 2:
        return None
    s, b = np.array(keep).T
    return float(np.polyfit(np.log(s), np.log(b), 1)[0])


def bias_study(res: int, args) -> dict:
    out = {}
    # (scene, reference, mode, max_depth, spp factor): the chromatic scene's bias is the
    # smallest, so it gets 4x the samples; `single` an eighth (its cost is quadratic)
    studies = [("smoke", "volpath", "multi", MAX_DEPTH, 1),
               ("chromatic", "volpath_delta", "multi", MAX_DEPTH, 4),
               ("sparse", "volpath", "multi", MAX_DEPTH, 1),
               ("smoke", "volpath", "single", 2, 1 / 8)]
    for scene_name, ref_name, mode, depth, factor in studies:
        scene = load(scene_name, res, depth)
        t = time.perf_counter()
        ref = Passes(scene, {"type": ref_name, "max_depth": depth}, 16, args.bias_ref_spp // 16,
                     seed=0)
        print(f"reference {scene_name} {ref_name} {depth}: {time.perf_counter() - t:.0f} s",
              flush=True)
        single = mode == "single"
        spp = int(args.bias_spp * factor)

        def march(step):
            return Passes(scene, {"type": "volpath_raymarch", "mode": mode, "max_depth": depth,
                                  "step_size": step}, args.bias_passes, spp, seed=1000)
        fine_step = SINGLE_FINE_STEP if single else FINE_STEP
        steps = SINGLE_STEPS if single else STEPS
        fine = march(fine_step)
        rows = []
        for step in steps:
            rows.append({"step": step, **paired_bias(march(step), fine)})
            print(f"  {scene_name} {mode} step {step}: {rows[-1]}", flush=True)
        resolved = [r for r in rows if r["bias2"] > 3 * r["noise"]]
        resolved_mean = [r for r in rows if abs(r["image_mean_bias"]) > 3 * r["image_mean_bias_se"]]
        out[f"{scene_name}_{mode}"] = {
            "reference": ref_name, "max_depth": depth, "rows": rows, "spp": spp,
            "fine_step": fine_step,
            "fine_vs_reference": {"step": fine_step, **independent_bias(fine, ref)},
            "order": order_of(steps, rows),
            "bias2_halvings_resolved": max(0, len(resolved) - 1),
            "bias2_decreasing": all(b["bias2"] < a["bias2"] for a, b in zip(resolved, resolved[1:])),
            "mean_bias_halvings_resolved": max(0, len(resolved_mean) - 1),
            "mean_bias_decreasing": all(abs(b["image_mean_bias"]) < abs(a["image_mean_bias"])
                                        for a, b in zip(resolved_mean, resolved_mean[1:]))}
        print(f"  fine vs reference: {out[f'{scene_name}_{mode}']['fine_vs_reference']}", flush=True)
    return out


def curve(scene, integrator: dict, ref: Passes, spp: int, budget: float) -> list:
    integ = mi.load_dict(integrator)
    timed_render(scene, integ, spp, seed=10 ** 8)                        # compile
    w = _weights(ref.mean)
    ref_noise = float(np.mean(ref.var * w))
    total, elapsed, points, k = None, 0.0, [], 0
    while elapsed < budget:
        t, img = timed_render(scene, integ, spp, seed=5000 + k)
        assert np.isfinite(img).all(), f"{integrator}: non-finite pixels"
        k += 1
        elapsed += t
        total = img.astype(np.float64) if total is None else total + img
        err = float(np.mean((total / k - ref.mean) ** 2 * w)) - ref_noise
        points.append((elapsed, k * spp, err))
    return points


def time_to_reach(points, target: float):
    """First time the error curve is at or below ``target`` (None if never)."""
    for t, _, e in points:
        if e <= target:
            return t
    return None


def curves(res: int, args) -> dict:
    out = {}
    for scene_name in ("smoke", "sparse"):
        scene = load(scene_name, res)
        t = time.perf_counter()
        ref = Passes(scene, {"type": "volpath", "max_depth": MAX_DEPTH}, 16, args.ref_spp // 16,
                     seed=0)
        print(f"reference {scene_name} volpath: {time.perf_counter() - t:.0f} s", flush=True)
        methods = {"volpath": {"type": "volpath", "max_depth": MAX_DEPTH},
                   "volpath_delta": {"type": "volpath_delta", "max_depth": MAX_DEPTH}}
        for step in CURVE_STEPS:
            methods[f"raymarch {step:g}"] = {"type": "volpath_raymarch", "max_depth": MAX_DEPTH,
                                             "step_size": step}
        out[scene_name] = {}
        for label, integrator in methods.items():
            out[scene_name][label] = curve(scene, integrator, ref, args.curve_spp, args.budget)
            print(f"  curve {scene_name} {label}: {len(out[scene_name][label])} passes, "
                  f"final error {out[scene_name][label][-1][2]:.2e}", flush=True)
    return out


def plot(curve_data: dict, bias: dict, outdir: Path) -> list:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    files = []
    for scene_name, methods in curve_data.items():
        fig, ax = plt.subplots(figsize=(6.4, 4.4))
        for label, points in methods.items():
            t, _, e = np.array(points).T
            ax.loglog(t, np.maximum(e, 1e-7), label=label,
                      linestyle="-" if "raymarch" in label else "--")
        rows = {r["step"]: r for r in bias[f"{scene_name}_multi"]["rows"]}
        for step in CURVE_STEPS:
            if step in rows and rows[step]["bias2"] > 0:
                ax.axhline(rows[step]["bias2"], color="gray", linewidth=0.6, linestyle=":")
        ax.set_xlabel("render time (s)")
        ax.set_ylabel("relative MSE (reference noise removed)")
        ax.set_title(f"{scene_name}: error against time (dotted: bias floors, from the bias study)", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = outdir / f"volpath_raymarch_{scene_name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        files.append(path.name)
    return files


def _fmt(x, digits=2):
    return "-" if x is None else f"{x:.{digits}e}"


def markdown(result: dict) -> str:
    cfg = result["config"]
    lines = [
        "# volpath_raymarch: bias per step, error against time",
        "",
        f"{result['date']}, {result['cpu']}, llvm_ad_rgb. "
        f"Command: `python3 -m benchmarks.volpath_raymarch` (this file is its output).",
        "",
        "## Bias per step size",
        "",
        f"{cfg['bias_res']}x{cfg['bias_res']} pixels. `mode=multi`, max_depth {MAX_DEPTH}: "
        f"{cfg['bias_passes']} passes per step (spp per pass below), each paired (same "
        f"seeds) with a fine march at step 1/64; `smoke_single`: `mode=single`, max_depth 2, "
        f"fine step 1/32. bias^2: squared relative error of the mean "
        "with the variance of the paired difference (`noise`) subtracted; below ~noise it is not "
        "resolved. Image-mean bias: mean(step) / mean(fine) - 1 +- its standard error. The "
        "media boxes are 2 units wide, 48 voxels (0.042) across.",
        "",
        "| scene | spp per pass | step | bias^2 (relMSE) | noise | image-mean bias | time (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, study in result["bias"].items():
        for r in study["rows"]:
            lines.append(f"| {name} | {study['spp']} | {r['step']:g} | {_fmt(r['bias2'])} | {_fmt(r['noise'])} | "
                         f"{100 * r['image_mean_bias']:+.4f}% +- {100 * r['image_mean_bias_se']:.4f}% "
                         f"| {r['seconds']:.1f} |")
    lines += ["", "The fine march (step 1/64; 1/32 for `single`) against the independent unbiased reference "
              f"({cfg['bias_ref_spp']} spp in 16 passes: volpath; volpath_delta for the chromatic "
              "scene, where volpath is biased):", "",
              "| scene | reference | bias^2 | noise | image-mean bias |", "|---|---|---|---|---|"]
    for name, study in result["bias"].items():
        r = study["fine_vs_reference"]
        lines.append(f"| {name} | {study['reference']} | {_fmt(r['bias2'])} | {_fmt(r['noise'])} | "
                     f"{100 * r['image_mean_bias']:+.4f}% +- {100 * r['image_mean_bias_se']:.4f}% |")
    lines += ["", "| scene | order k (image-mean bias ~ step^k) | halvings with bias^2 resolved: "
                  "falls at each? | halvings with image-mean bias resolved: falls at each? |",
              "|---|---|---|---|"]
    for name, study in result["bias"].items():
        order = "-" if study["order"] is None else f"{study['order']:.2f}"
        lines.append(f"| {name} | {order} | {study['bias2_halvings_resolved']}: "
                     f"{'yes' if study['bias2_decreasing'] else 'NO'} | "
                     f"{study['mean_bias_halvings_resolved']}: "
                     f"{'yes' if study['mean_bias_decreasing'] else 'NO'} |")
    lines += ["", "## Error against time", "",
              f"{cfg['res']}x{cfg['res']} pixels. Passes of {cfg['curve_spp']} spp until "
              f"{cfg['budget']:g} s; relative MSE of the running mean against a volpath "
              f"reference ({cfg['ref_spp']} spp) minus the reference's variance. Time "
              "(s) to reach each error; `-`: not reached within the budget (for raymarch: "
              "below its bias floor, or not yet). Fastest in bold.", ""]
    for scene_name, methods in result["curves"].items():
        lines += [f"### {scene_name}", "", f"![{scene_name}](volpath_raymarch_{scene_name}.png)",
                  "", "| method | " + " | ".join(f"relMSE {e:g}" for e in TARGET_ERRORS)
                  + " | final relMSE | spp reached |",
                  "|---|" + "---|" * (len(TARGET_ERRORS) + 2)]
        times = {label: [time_to_reach(points, e) for e in TARGET_ERRORS]
                 for label, points in methods.items()}
        best = [min((t[i] for t in times.values() if t[i] is not None), default=None)
                for i in range(len(TARGET_ERRORS))]
        for label, points in methods.items():
            cells = []
            for i, t in enumerate(times[label]):
                text = "-" if t is None else f"{t:.2f}"
                cells.append(f"**{text}**" if t is not None and t == best[i] else text)
            lines.append(f"| {label} | " + " | ".join(cells) + f" | {_fmt(points[-1][2])} | "
                         f"{points[-1][1]} |")
        lines.append("")
    return "\n".join(lines) + "\n"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--res", type=int, default=64)
    parser.add_argument("--ref-spp", type=int, default=4096)
    parser.add_argument("--bias-res", type=int, default=16)
    parser.add_argument("--bias-ref-spp", type=int, default=65536)
    parser.add_argument("--bias-passes", type=int, default=8)
    parser.add_argument("--bias-spp", type=int, default=16384)
    parser.add_argument("--curve-spp", type=int, default=4)
    parser.add_argument("--budget", type=float, default=20.0)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    bias = bias_study(args.bias_res, args)
    curve_data = curves(args.res, args)
    result = {"date": datetime.date.today().isoformat(), "cpu": cpu_model(),
              "config": {"res": args.res, "ref_spp": args.ref_spp, "bias_res": args.bias_res,
                         "bias_ref_spp": args.bias_ref_spp, "bias_passes": args.bias_passes,
                         "bias_spp": args.bias_spp, "curve_spp": args.curve_spp,
                         "budget": args.budget, "steps": STEPS, "curve_steps": CURVE_STEPS},
              "bias": bias, "curves": curve_data}
    result["plots"] = plot(curve_data, bias, args.out)
    result["total_seconds"] = time.perf_counter() - t0
    output.write_json(args.out / "volpath_raymarch.json", result, indent=1)
    output.write_text(args.out / "volpath_raymarch.md", markdown(result))
    print(markdown(result))
    print(f"total {result['total_seconds']:.0f} s")


if __name__ == "__main__":
    main()
