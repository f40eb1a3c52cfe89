"""Validation on Mitsuba's own participating-media render tests, in any variant.

Mitsuba's regression scenes (the ``mitsuba-data`` repository, folder
``<mitsuba-data>/tests/scenes/participating_media``; not shipped here: clone it and pass ``--data``) are
rendered with the Mitsuba integrator each scene names (the reference: ``volpath``, or
``volpathmis`` for the two ``*_volpathmis`` scenes of strongly chromatic extinction, where
``volpath``'s one-channel distance sampling is heavy-tailed; docs/validation.md) and with
our integrators, each as
``--passes`` independent passes (other seeds than the reference's), and compared with
the project's three checks (docs/validation.md: per-pixel Welch test with Sidak
correction, 8x8 block means, image mean; :func:`mitsuba_plugins.tools.stats.compare`).
Every scene's own ``max_depth`` (6) is kept. Results go to
``benchmarks/results/corpus_<variant>.{md,json}``.

    git clone https://github.com/mitsuba-renderer/mitsuba-data
    python3 -m benchmarks.corpus --data mitsuba-data --variant llvm_ad_spectral
"""
from __future__ import annotations

import argparse
import datetime
import json
import time
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import mitsuba as mi
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FOLDER = Path("tests") / "scenes" / "participating_media"
INTEGRATORS = ("volpath_delta", "volpath_raymarch")
#: the scenes' own depth (include/test-scene-base.xml)
MAX_DEPTH = 6


def scenes(data: Path) -> list:
    return sorted((data / FOLDER).glob("test_*.xml"))


def run(data: Path, variant: str, res: int, passes: int, spp: int, integrators,
        only=None, seed: int = 0, reference: str | None = None) -> list:
    mi.set_variant(variant)
    from mitsuba_plugins.tools import stats
    rows = []
    for path in scenes(data):
        if only and not any(o in path.stem for o in only):
            continue
        named = reference or path.stem.rsplit("_", 1)[-1]   # volpath or volpathmis
        scene = mi.load_file(str(path), res=res, integrator=named)
        t0 = time.perf_counter()
        ref = stats.render_passes(scene, passes, spp, mi.load_dict(
            {"type": named, "max_depth": MAX_DEPTH}), seed=seed)
        for name in integrators:
            est = stats.render_passes(scene, passes, spp, mi.load_dict(
                {"type": name, "max_depth": MAX_DEPTH}), seed=seed + 1000)
            result = stats.compare(est, ref)
            rows.append({"scene": path.stem, "integrator": name, "reference": named,
                         "passed": result.passed,
                         "pixel_fail_percent": 100 * result.pixel_fail_fraction,
                         "block_failures": result.block_failures,
                         "mean_z": result.mean_z.tolist(),
                         "mean": est.mean.mean(axis=(0, 1)).tolist(),
                         "reference_mean": ref.mean.mean(axis=(0, 1)).tolist(),
                         "invalid": est.invalid + ref.invalid})
            print(f"{path.stem:50s} {name:18s} {'pass' if result.passed else 'FAIL'}  "
                  f"{result.summary()}", flush=True)
        print(f"  ({time.perf_counter() - t0:.0f} s)", flush=True)
    return rows


def write(rows: list, variant: str, args) -> None:
    from mitsuba_plugins import output
    out = ROOT / "benchmarks" / "results" / f"corpus_{variant}"
    when = datetime.date.today().isoformat()
    settings = (f"{args.res}x{args.res}, {args.passes} passes x {args.spp} spp per "
                f"integrator, the reference (the integrator the scene names) with other "
                f"seeds; {when}")
    lines = [f"# Mitsuba's participating-media render tests, `{variant}`", "",
             f"_From `python3 -m benchmarks.corpus --variant {variant}` ({settings}). "
             "Checks: docs/validation.md (per-pixel Welch test, 8x8 blocks, image mean)._",
             "", "| scene | integrator | reference | result | pixels failing | blocks failing | "
             "image-mean z | image mean (ours / reference) | NaN/Inf |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        z = ", ".join(f"{v:+.2f}" for v in r["mean_z"])
        mean = f"{np.mean(r['mean']):.4g} / {np.mean(r['reference_mean']):.4g}"
        lines.append(f"| {r['scene']} | `{r['integrator']}` | `{r['reference']}` | "
                     f"{'pass' if r['passed'] else '**FAIL**'} | {r['pixel_fail_percent']:.3f}% | "
                     f"{r['block_failures']} | {z} | {mean} | {r['invalid']} |")
    output.write_text(out.with_suffix(".md"), "\n".join(lines) + "\n")
    output.write_text(out.with_suffix(".json"), json.dumps(
        {"variant": variant, "settings": settings, "rows": rows}, indent=1) + "\n")
    print(f"wrote {out}.md")


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, type=Path, help="a mitsuba-data checkout")
    p.add_argument("--variant", default="llvm_ad_spectral")
    p.add_argument("--res", type=int, default=32)
    p.add_argument("--passes", type=int, default=8)
    p.add_argument("--spp", type=int, default=256, help="samples per pixel per pass")
    p.add_argument("--integrators", default=",".join(INTEGRATORS))
    p.add_argument("--only", help="comma-separated parts of scene names")
    p.add_argument("--reference", help="reference integrator of every scene (default: the "
                                       "one each scene names)")
    p.add_argument("--no-write", action="store_true")
    args = p.parse_args()
    rows = run(args.data, args.variant, args.res, args.passes, args.spp,
               args.integrators.split(","), args.only.split(",") if args.only else None,
               reference=args.reference)
    if not args.no_write:
        write(rows, args.variant, args)
    failed = [r for r in rows if not r["passed"]]
    print(f"{len(rows) - len(failed)} passed, {len(failed)} failed")


if __name__ == "__main__":
    main()
