"""Issue 48, part 3: where the heavy tail of ``drt``'s gradients comes from.

On the gray smoke (``benchmarks.inverse.smoke_scene``, scale 8, 32^2) the derivative of
the mean image along issue 26's direction (a smooth field times the density) is rendered
``--runs`` times in forward mode (one derivative image per render, 32 spp, max_depth 16)
for ``drt`` and ``sm`` (``prbvolpath`` has no forward mode). Pixels are independent, so
the variance of the scalar derivative is the sum of the pixels' variances over the pixel
count squared: the per-pixel variance says where it comes from. Reported per method: the
scalar's standard deviation, its excess kurtosis and the renders beyond 3 standard
deviations; the share of the variance held by the 1% and 5% of pixels with the most, and
those pixels' primal radiance (above 20: the light, radiance 40, seen directly); and the
split of the derivative's variance between the estimator's terms
(``mitsuba_plugins.instrument.only_terms``: light reached by emitter sampling, ``nee``,
or by hitting an emitter, ``emission``).

``python3 -m benchmarks.gradient_tail [--runs N]`` writes
``benchmarks/results/gradient_tail.{md,json}``.
"""
from __future__ import annotations

import argparse
import datetime
import json
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- picks libLLVM first
import mitsuba as mi
import numpy as np

from mitsuba_plugins.registry import default_variant

ROOT = Path(__file__).resolve().parents[1]
#: ours only: prbvolpath has no forward mode (its variance: benchmarks.inverse)
METHODS = {"drt": {"type": "volpath_delta", "gradient_estimator": "drt"},
           "sm": {"type": "volpath_delta", "gradient_estimator": "sm"}}


def kurtosis(x) -> float:
    x = np.asarray(x, np.float64)
    d = x - x.mean()
    return float(np.mean(d ** 4) / np.mean(d ** 2) ** 2 - 3.0)


def derivative_images(scene, params, direction, integrator, runs, spp, terms=None):
    from mitsuba_plugins.instrument import only_terms
    from mitsuba_plugins.tools.gradcheck import forward_image
    images = []
    for seed in range(runs):
        if terms is None:
            images.append(forward_image(scene, params, direction, integrator, seed, spp))
        else:
            with only_terms(*terms):
                images.append(forward_image(scene, params, direction, integrator, seed, spp))
    return np.stack(images).mean(axis=-1)          # runs x H x W (channel mean)


def study(runs: int, spp: int) -> dict:
    from benchmarks.inverse import density_key, smoke_scene
    from mitsuba_plugins.tools.gradcheck import smooth_direction
    scene = smoke_scene(8.0, res=32)
    params = mi.traverse(scene)
    key = density_key(params)
    direction = {key: smooth_direction(np.array(params[key]).shape) * np.array(params[key])}
    primal = np.array(mi.render(scene, integrator=mi.load_dict({"type": "volpath_delta"}),
                                spp=1024, seed=99)).mean(axis=-1)
    out = {"runs": runs, "spp": spp, "methods": {}}
    for name, desc in METHODS.items():
        integrator = mi.load_dict(dict(desc, max_depth=16))
        imgs = derivative_images(scene, params, direction, integrator, runs, spp)
        scalars = imgs.mean(axis=(1, 2))
        var_px = imgs.var(axis=0, ddof=1)
        order = np.sort(var_px.ravel())[::-1]
        n = order.size
        z = (scalars - scalars.mean()) / scalars.std(ddof=1)
        top = np.argsort(var_px.ravel())[::-1][: max(1, n // 100)]
        row = {"mean": float(scalars.mean()), "std": float(scalars.std(ddof=1)),
               "excess_kurtosis": kurtosis(scalars),
               "beyond_3_sigma": int(np.sum(np.abs(z) > 3)),
               "share_top1pct": float(order[: max(1, n // 100)].sum() / order.sum()),
               "share_top5pct": float(order[: max(1, n // 20)].sum() / order.sum()),
               "top_pixels": [{"pixel": [int(i // imgs.shape[2]), int(i % imgs.shape[2])],
                               "primal": float(primal.ravel()[i]),
                               "variance_share": float(var_px.ravel()[i] / order.sum()),
                               "pixel_kurtosis": kurtosis(imgs.reshape(runs, -1)[:, i])}
                              for i in top],
               "values": [float(v) for v in scalars]}
        split = {}
        for terms in (("nee",), ("emission",)):
            t_imgs = derivative_images(scene, params, direction, integrator, runs, spp, terms)
            split["+".join(terms)] = {
                "variance_of_scalar": float(t_imgs.mean(axis=(1, 2)).var(ddof=1)),
                "excess_kurtosis": kurtosis(t_imgs.mean(axis=(1, 2)))}
        row["terms"] = split
        out["methods"][name] = row
        print(name, json.dumps({k: v for k, v in row.items()
                                if k not in ("values", "top_pixels")}), flush=True)
    out["primal_light_pixels"] = int(np.sum(primal > 20.0))
    return out


def markdown(r) -> str:
    lines = ["# The heavy tail of gradient renders (issue 48, part 3)", "",
             f"Measured {r['date']} on {r['device']} ({r['variant']}) by `python3 -m "
             f"benchmarks.gradient_tail {r['argv']}`: {r['runs']} forward-mode derivative "
             f"images per method, {r['spp']} spp, 32^2, the gray smoke (scale 8), max_depth "
             "16 (benchmarks/gradient_tail.py says how).", "",
             "| method | derivative | std | excess kurtosis | renders beyond 3 sigma | "
             "variance in the top 1% / 5% of pixels |", "|---|---|---|---|---|---|"]
    for m, x in r["methods"].items():
        lines.append(f"| {m} | {x['mean']:+.5f} | {x['std']:.5f} | {x['excess_kurtosis']:.2f} | "
                     f"{x['beyond_3_sigma']} of {r['runs']} | {x['share_top1pct']:.2f} / "
                     f"{x['share_top5pct']:.2f} |")
    lines += ["", "Pixels holding the most variance (drt): pixel, primal radiance, share of "
              "the variance, the pixel's own excess kurtosis over the renders:", ""]
    for p in r["methods"]["drt"]["top_pixels"]:
        lines.append(f"- {tuple(p['pixel'])}: primal {p['primal']:.3f}, share "
                     f"{p['variance_share']:.3f}, kurtosis {p['pixel_kurtosis']:.1f}")
    for m, x in r["methods"].items():
        total = x["std"] ** 2
        lines += ["", f"Variance of the derivative by term ({m}; the two sum to the whole "
                  "up to their covariance):", ""]
        for k, v in x["terms"].items():
            lines.append(f"- {k} only: {v['variance_of_scalar'] / total:.2f} of the "
                         f"variance, excess kurtosis {v['excess_kurtosis']:.2f}")
    return "\n".join(lines) + "\n"


def main() -> None:
    import sys
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=64)
    ap.add_argument("--spp", type=int, default=32)
    args = ap.parse_args()
    variant = default_variant()
    mi.set_variant(variant)
    from benchmarks.harness import device_model
    r = study(args.runs, args.spp)
    r.update(date=datetime.date.today().isoformat(), device=device_model(variant),
             variant=variant, argv=" ".join(sys.argv[1:]))
    out = ROOT / "benchmarks" / "results" / "gradient_tail"
    out.with_suffix(".json").write_text(json.dumps(r, indent=1))
    out.with_suffix(".md").write_text(markdown(r))
    print(markdown(r))


if __name__ == "__main__":
    main()
