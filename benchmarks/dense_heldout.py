"""Dense media, held out (issue 29): a generated family of 24 scenes split by seed into a
tuning half (even seeds) and a test half (odd seeds); volpath_delta against Mitsuba's
volpath at equal time on both, defaults chosen on the tuning half only.

The family is stratified so that each half holds every kind of light and medium: pair
``i`` (seeds ``2i`` and ``2i + 1``) shares its light, ``LIGHTS[i % 6]`` (a small area
light, a point light, a spot light, sun + sky, an environment map, the camera inside the
medium), and its shape, ``SHAPES[i % 4]`` (a plume or a cumulus grid, held by
``grid_medium`` or by Mitsuba's ``heterogeneous`` + ``gridvolume`` as a user's existing
scene would; a homogeneous sphere; a homogeneous cube of extinction 1e4 beside a
near-empty one). Everything else is drawn from the seed: max/mean 2-20, optical depth
(grids 2-60, spheres 5-200 through the middle), albedo 0.8-0.999 (gray or tinted), HG
g in [-0.9, 0.95], the grid's medium plugin. The camera inside a cube pair sits in the
near-empty cube, looking at the dense one.

Each scene: a reference of :data:`dense.REFERENCE` (``--ref-spp``), then
:func:`dense.equal_time` (both compiled first; volpath at ``--spp``, ours at the spp
that takes as long; ``--runs`` alternating renders; efficiency = 1 / (mean relMSE x
median time), its 90% bootstrap interval over runs), and the relative MSE per sample
against volpath's (``rel_mse_per_sample_ratio``: below 1 means lower variance per
sample).

``python3 -m benchmarks.dense_heldout --half tuning`` / ``--half test`` (default: both);
writes ``benchmarks/results/dense_heldout.{md,json}``.
"""
from __future__ import annotations

import argparse
import datetime
import statistics
import sys
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import mitsuba as mi
import numpy as np

from benchmarks import dense  # sets the variant
from benchmarks.harness import device_model
from mitsuba_plugins import output
from mitsuba_plugins.grids import gridio

ROOT = Path(__file__).resolve().parents[1]
LIGHTS = ("area", "point", "spot", "sun", "env", "inside")
SHAPES = ("plume", "cumulus", "sphere", "cube_pair")
PAIRS = 12
#: extinction of the dense cube of a cube pair, and of its near-empty neighbour
PAIR_DENSE, PAIR_THIN = 1e4, 0.05
TARGET_MEDIAN, TARGET_MIN = 3.0, 1.5


@dataclass(frozen=True)
class HeldCase:
    name: str
    half: str              # tuning | test
    seed: int
    shape: str             # plume | cumulus | sphere | cube_pair
    plugin: str            # grid_medium | heterogeneous | homogeneous
    max_over_mean: float   # of the density grid (1 for homogeneous)
    tau: float             # optical depth through the middle (extinction x 2)
    albedo: tuple          # RGB
    g: float
    light: str


def family() -> list:
    cases = []
    for i in range(PAIRS):
        light, shape = LIGHTS[i % len(LIGHTS)], SHAPES[i % len(SHAPES)]
        for seed in (2 * i, 2 * i + 1):
            rng = np.random.default_rng(29_000 + seed)
            albedo = 1.0 - 10 ** rng.uniform(-3.0, np.log10(0.2))
            tint = (1.0, *rng.uniform(0.85, 1.0, 2)) if rng.random() < 0.5 else (1.0, 1.0, 1.0)
            rgb = tuple(round(max(0.8, float(albedo * t)), 4) for t in tint)   # 0.8-0.999
            g = float(rng.uniform(-0.9, 0.95))
            if shape in ("plume", "cumulus"):
                plugin = ("grid_medium", "heterogeneous")[int(rng.integers(2))]
                mom = float(10 ** rng.uniform(np.log10(2), np.log10(20)))
                tau = float(10 ** rng.uniform(np.log10(2), np.log10(60)))
            elif shape == "sphere":
                plugin, mom, tau = "homogeneous", 1.0, float(10 ** rng.uniform(np.log10(5), 2.3))
            else:
                plugin, mom, tau = "homogeneous", 1.0, 2 * PAIR_DENSE
            half = "tuning" if seed % 2 == 0 else "test"
            cases.append(HeldCase(f"{half}{seed:02d}_{shape}_{light}", half, seed, shape, plugin,
                                  round(mom, 2), round(tau, 2),
                                  rgb, round(g, 3), light))
    return cases


# -- scenes -----------------------------------------------------------------------------------
def _rgb(value) -> dict:
    return {"type": "rgb", "value": list(value)}


def _medium(case: HeldCase, tmp: Path) -> dict:
    common = {"albedo": _rgb(case.albedo), "phase": {"type": "hg", "g": case.g}}
    if case.plugin == "homogeneous":
        return {"type": "homogeneous", "sigma_t": case.tau / 2, **common}
    data = dense.density(case.shape, case.max_over_mean, seed=case.seed)
    to_world = mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)
    if case.plugin == "grid_medium":
        path = tmp / f"{case.name}.npy"
        np.save(path, data)
        return {"type": "grid_medium", "filename": str(path), "scale": case.tau / 2,
                "to_world": to_world, **common}
    path = tmp / f"{case.name}.vol"
    gridio.write_vol(path, data[..., None])
    return {"type": "heterogeneous", "scale": case.tau / 2, **common,
            "sigma_t": {"type": "gridvolume", "filename": str(path), "to_world": to_world}}


def _sensor(res: int, origin, target, medium=None) -> dict:
    d = {"type": "perspective", "fov": 40 if medium is None else 60,
         "to_world": mi.ScalarTransform4f().look_at(origin, target, [0, 1, 0]),
         "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
         "sampler": {"type": "independent", "sample_count": 16}}
    if medium is not None:
        d["medium"] = {"type": "ref", "id": medium}
    return d


def scene(case: HeldCase, res: int, tmp: Path) -> mi.Scene:
    d = {"type": "scene", "medium": {**_medium(case, tmp), "id": "medium"}}
    null = {"type": "null"}
    if case.shape == "cube_pair":
        d["dense_cube"] = {"type": "cube", "bsdf": null, "interior": {"type": "ref", "id": "medium"},
                           "to_world": mi.ScalarTransform4f().translate([-0.55, 0, 0]).scale(0.5)}
        d["thin"] = {**_medium(HeldCase("thin", case.half, case.seed, "sphere", "homogeneous", 1.0,
                                        2 * PAIR_THIN, case.albedo, case.g, case.light), tmp),
                     "id": "thin"}
        d["thin_cube"] = {"type": "cube", "bsdf": null, "interior": {"type": "ref", "id": "thin"},
                          "to_world": mi.ScalarTransform4f().translate([0.55, 0, 0]).scale(0.5)}
        inside = "thin"
        view = ([0.7, 0.1, 0.3], [-0.6, 0.0, -0.1])
    else:
        shape = {"type": "sphere"} if case.shape == "sphere" else {"type": "cube"}
        d["volume"] = {**shape, "bsdf": null, "interior": {"type": "ref", "id": "medium"}}
        inside = "medium"
        view = ([0.15, -0.3, 0.75], [-0.1, 0.25, -1.0])
    if case.light == "inside":
        d["sensor"] = _sensor(res, *view, medium=inside)
    else:
        d["sensor"] = _sensor(res, [0.2, 0.9, 3.2], [0, 0, 0])
    floor = {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": _rgb([0.5] * 3)},
             "to_world": mi.ScalarTransform4f().translate([0, -1.0, 0]).rotate(
                 [1, 0, 0], -90).scale(3)}
    dim_sky = {"type": "constant", "radiance": _rgb([0.03] * 3)}
    if case.light in ("area", "inside"):
        d.update(floor=floor, sky=dim_sky,
                 light={"type": "sphere", "center": [2.0, 2.5, 1.5], "radius": 0.12,
                        "emitter": {"type": "area", "radiance": _rgb([150.0] * 3)}})
    elif case.light == "point":
        d.update(floor=floor, sky=dim_sky,
                 light={"type": "point", "position": [2.0, 2.5, 1.5],
                        "intensity": _rgb([8.0] * 3)})
    elif case.light == "spot":
        d.update(floor=floor, sky=dim_sky,
                 light={"type": "spot", "cutoff_angle": 25.0, "intensity": _rgb([20.0] * 3),
                        "to_world": mi.ScalarTransform4f().look_at([1.5, 3.0, 1.5], [0, 0, 0],
                                                                   [0, 1, 0])})
    elif case.light == "sun":
        d.update(floor=floor, sky={"type": "constant", "radiance": _rgb([0.1, 0.15, 0.25])},
                 sun={"type": "directional", "direction": [-0.6, -1.0, -0.4],
                      "irradiance": _rgb([3.0] * 3)})
    else:
        d.update(env={"type": "envmap", "filename": dense.sky(tmp)})
    return mi.load_dict(d)


# -- measurement ------------------------------------------------------------------------------
def measure(case: HeldCase, variants: dict, res: int, spp: int, runs: int, ref_spp: int,
            tmp: Path) -> dict:
    sc = scene(case, res, tmp)
    ref = dense.reference(sc, ref_spp)
    eff = dense.equal_time(sc, variants, spp, runs, ref)
    for k in variants:
        r = eff[k]
        # relMSE x spp: the relative MSE of one sample, ours over volpath's
        r["rel_mse_per_sample_ratio"] = (r["rel_mse"] * r["spp"]) / \
            (eff["builtin"]["rel_mse"] * eff["builtin"]["spp"])
    return {"case": asdict(case), "efficiency": eff}


def summary(cases: dict, variant: str, half: str) -> dict:
    rows = [r["efficiency"][variant] for r in cases.values() if r["case"]["half"] == half]
    if not rows:
        return {}
    eff = [r["efficiency_ratio"] for r in rows]
    return {"n": len(rows), "median": statistics.median(eff), "min": min(eff),
            "lower_variance": sum(r["rel_mse_per_sample_ratio"] < 1 for r in rows)}


def markdown(result: dict) -> str:
    cfg = result["config"]
    variants = cfg["variants"]
    lines = ["# Dense media, held out: volpath_delta against Mitsuba's volpath", "",
             f"Measured {result['date']} on {result['cpu']} ({dense.VARIANT}, Mitsuba "
             f"{mi.__version__}) by `python3 -m benchmarks.dense_heldout {cfg['argv']}` (res "
             f"{cfg['res']}, volpath {cfg['spp']} spp, {cfg['runs']} alternating runs at equal "
             f"time, median time, mean relMSE; time/spp: measured time per sample over volpath's; reference {cfg['ref_spp']} spp of "
             f"{cfg['reference']}). Family and method: the script's docstring. Targets (test "
             f"half): median >= {TARGET_MEDIAN}x, none below {TARGET_MIN}x; relMSE per sample "
             "below volpath's on at least half.", ""]
    for half in ("tuning", "test"):
        rows = {k: r for k, r in result["cases"].items() if r["case"]["half"] == half}
        if not rows:
            continue
        lines += [f"## {half.capitalize()} half", "",
                  "| scene | medium | max/mean | tau | albedo | g | " + " | ".join(
                      f"{v}: efficiency (90%), time/spp, relMSE/sample" for v in variants) + " |",
                  "|---|---|---|---|---|---|" + "---|" * len(variants)]
        for name, r in rows.items():
            c, e = r["case"], r["efficiency"]
            lines.append(
                f"| {name} | {c['plugin']} | {c['max_over_mean']:g} | {c['tau']:g} | "
                f"{'/'.join(f'{a:g}' for a in c['albedo'])} | {c['g']:g} | " + " | ".join(
                    f"**{e[v]['efficiency_ratio']:.2f}x** ({e[v]['efficiency_ratio_90'][0]:.2f}-"
                    f"{e[v]['efficiency_ratio_90'][1]:.2f}), "
                    f"{dense.time_per_sample_ratio(e, v):.2f}, "
                    f"{e[v]['rel_mse_per_sample_ratio']:.2f}{dense.guided_runs_note(e[v])}"
                    for v in variants) + " |")
        lines.append("")
        for v in variants:
            s = summary(rows, v, half)
            met = s["median"] >= TARGET_MEDIAN and s["min"] >= TARGET_MIN
            lines.append(f"- {v}: median **{s['median']:.2f}x**, min **{s['min']:.2f}x**, "
                         f"relMSE per sample below volpath's on {s['lower_variance']} of "
                         f"{s['n']}" + (f" ({'meets' if met else 'MISSES'} the targets)"
                                        if half == "test" else ""))
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--runs", type=int, default=6)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--half", choices=("tuning", "test", "both"), default="both")
    ap.add_argument("--cases", default="", help="names to run (default: the half's)")
    ap.add_argument("--variants", default="volpath_delta",
                    help="configurations of benchmarks/dense.py's VARIANTS")
    ap.add_argument("--list", action="store_true", help="print the family and exit")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "dense_heldout"))
    args = ap.parse_args()
    cases = [c for c in family() if args.half in ("both", c.half)
             and (not args.cases or c.name in args.cases.split(","))]
    if args.list:
        for c in cases:
            print(c)
        return
    variants = {v: dense.VARIANTS[v] for v in args.variants.split(",")}
    out = Path(args.out)
    result = {"date": datetime.date.today().isoformat(), "cpu": device_model(dense.VARIANT),
              "variant": dense.VARIANT, "cases": {},
              "config": {"res": args.res, "spp": args.spp, "runs": args.runs,
                         "ref_spp": args.ref_spp, "reference": dense.REFERENCE,
                         "variants": list(variants), "argv": " ".join(sys.argv[1:])}}
    with tempfile.TemporaryDirectory() as tmpdir:
        for case in cases:
            r = measure(case, variants, args.res, args.spp, args.runs, args.ref_spp,
                        Path(tmpdir))
            result["cases"][case.name] = r
            print(case.name, ", ".join(
                f"{v} {r['efficiency'][v]['efficiency_ratio']:.2f}x "
                f"(relMSE/sample {r['efficiency'][v]['rel_mse_per_sample_ratio']:.2f})"
                for v in variants), flush=True)
            output.write_json(out.with_suffix(".json"), result, indent=1)
            output.write_text(out.with_suffix(".md"), markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
