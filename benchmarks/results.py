"""Regenerate docs/results.md: the scene gallery at equal time (tables, error-against-time
curves, image panels) and the scale table (time and peak memory against image size, spp
and grid resolution), then the summary block of the README.

    python3 -m benchmarks.results              # about 20 minutes on 2 cores, from scratch
    python3 -m benchmarks.results --quick      # smoke run: tiny budgets, nothing committed
    python3 -m benchmarks.results --variant cuda_ad_rgb --no-scale   # GPU gallery

In a variant other than llvm_ad_rgb the gallery goes to ``docs/results_<variant>.md`` (figures
in ``docs/results_<variant>/``) and the README's summary is left alone.

Gallery: each scene is measured with ``mitsuba_plugins.tools.compare`` in equal-time mode (every
integrator renders 16-spp passes, taking turns, until its budget is spent; compilation
excluded) against a reference from the matching built-in, rendered here from scratch
(``--keep-references`` reuses a previous run's). A reference's own noise is subtracted
from every rel. MSE (its share is printed in each table's legend).

Scale: every configuration runs in a fresh process (``--scale-worker``) so that its peak
resident memory (``VmHWM``) is its own; times are the median of 3 renders after a
warm-up render.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.harness import device_model, status_mib

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
FIGURES = DOCS / "results"
README = ROOT / "README.md"
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"

VOLUME = ("volpath_delta:max_depth=16", "volpath_raymarch:max_depth=16", "volpath:max_depth=16")
#: Media references are volpath_delta's (independent seeds): in a minute it renders 10-20x
#: the samples volpath would (a first run with volpath references at 60 s had only 560
#: spp on the sparse scene, less than ours reach in the budget), its agreement with
#: volpath is what tests/integrators/test_volpath_delta.py checks, and volpath is biased for
#: chromatic extinction (tests/integrators/test_stability.py).
MEDIA_REFERENCE = "volpath_delta:max_depth=16"
#: the gallery: scene, integrators (ours first, then the built-ins), reference override
GALLERY = [
    ("cornell_box", ("direct_mis", "direct", "path_rr", "path"), None),
    ("veach_mis", ("direct_mis", "direct", "path_rr:max_depth=2", "path:max_depth=2"), None),
    ("smoke", VOLUME, MEDIA_REFERENCE),
    ("sparse", VOLUME, MEDIA_REFERENCE),
    ("chromatic", VOLUME, MEDIA_REFERENCE),
    # Mitsuba's built-ins ignore medium emission: ours only (scenes/fire.xml)
    ("fire", VOLUME[:2], MEDIA_REFERENCE),
]
#: benchmarks/underflow.py's table and panel, included as a section when present
UNDERFLOW = ROOT / "benchmarks" / "results" / "underflow.md"
HEADLINE = "sparse"   # the README's plot
SCALE_NOTE = (
    "Memory stays bounded without any splitting: in Dr.Jit's LLVM backend a whole render "
    "is one kernel whose per-sample state lives in registers and whose sample indices are "
    "computed in the kernel, so peak memory follows the film, not the sample count (compare "
    "the spp rows, and 1024^2 at 16 and 64 spp). Mitsuba's `samples_per_pass` (accepted "
    "by every plugin here) renders in passes of that many spp; on this backend it does not "
    "lower peak memory (see its rows). Grids are stored once: peak memory grows by about "
    "the grid's size (4 bytes a voxel), while rendering time changes little with the "
    "resolution of the same density field.")
RES = 128


# -- gallery ----------------------------------------------------------------------------------
def reference_spp(scene, reference: dict, seconds: float) -> int:
    """Reference spp for about ``seconds`` of rendering: a 4-spp pilot pass, timed after
    a warm-up, scaled (a multiple of 16, at least 256)."""
    import drjit as dr
    import mitsuba as mi
    integrator = mi.load_dict(reference)
    for seed in (1, 2):                     # the first compiles
        t0 = time.perf_counter()
        img = mi.render(scene, integrator=integrator, spp=4, seed=seed)
        dr.eval(img)
        dr.sync_thread()
        pilot = time.perf_counter() - t0
    return max(256, int(seconds / pilot * 4) // 16 * 16)


def gallery_cell(name: str, specs: list, reference, budget: float, ref_seconds: float,
                 cache: str, scheduler: str | None = None, variant: str | None = None):
    """One scene of the gallery: its reference spp (a timed pilot), then ``compare`` at
    equal time. Returns ``(result, ref_spp, seconds)``. Runs here or as a Dask task on a
    worker (``variant`` is then set there); every row of a cell is timed on the machine
    that runs the cell."""
    import mitsuba as mi
    if variant and mi.variant() != variant:
        mi.set_variant(variant)
    from mitsuba_plugins.tools.compare import compare
    from mitsuba_plugins.tools.integrator_specs import parse_integrator, reference_for
    from mitsuba_plugins.tools.scenes import load_scene
    path = str(ROOT / "scenes" / f"{name}.xml")
    integrators = [parse_integrator(s) for s in specs]
    ref = parse_integrator(reference) if reference else None
    refs = [ref] if ref else list({json.dumps(reference_for(i), sort_keys=True): reference_for(i)
                                   for i in integrators}.values())
    scene = load_scene(path, RES)
    ref_spp = max(reference_spp(scene, r, ref_seconds) for r in refs)
    t0 = time.perf_counter()
    result = compare(path, integrators, time_budget=budget, spp_per_pass=16, ref_spp=ref_spp,
                     res=RES, cache_dir=Path(cache), progress=False, reference=ref,
                     scheduler=scheduler)
    result.scene = f"scenes/{name}.xml"     # as the docs name it, wherever it ran
    return result, ref_spp, time.perf_counter() - t0


def gallery(budget: float, ref_seconds: float, cache: Path, only: list | None,
            scheduler: str | None = None, cells: bool = False) -> list:
    """The gallery's cells in order. ``scheduler``: references render as tasks there;
    with ``cells``, each whole cell is one task instead (its timed rows on one worker)."""
    import mitsuba as mi
    from mitsuba_plugins import output
    from mitsuba_plugins.tools import report, viewer
    todo = [(name, specs, reference) for name, specs, reference in GALLERY
            if not only or name in only]
    if cells:
        from mitsuba_plugins.tools.reference import close, connect
        client, _ = connect(scheduler=scheduler)
        try:
            futures = [client.submit(gallery_cell, name, specs, reference, budget, ref_seconds,
                                     str(cache), None, mi.variant(), pure=False)
                       for name, specs, reference in todo]
            outcomes = client.gather(futures)
        finally:
            close(client)
    else:
        outcomes = [gallery_cell(name, specs, reference, budget, ref_seconds, str(cache),
                                 scheduler) for name, specs, reference in todo]
    results = []
    for (name, _, _), (result, ref_spp, seconds) in zip(todo, outcomes):
        print(f"{name}: {seconds:.0f} s (reference {ref_spp} spp)", flush=True)
        curves = report.plot_curves(result, FIGURES / f"{name}_curves.png")
        report.plot_panel(result, FIGURES / f"{name}_panel.png")
        output.write_json(FIGURES / f"{name}.json", result.to_dict(), indent=1)
        viewer.write_page(result, FIGURES / f"{name}.html", report.COLUMNS, report.legend(result),
                          curves=curves, title=f"{name} (equal time, {budget:g} s)",
                          links={"all scenes": "index.html"})
        results.append((name, result))
    viewer.write_index(FIGURES / "index.html", "mitsuba_plugins: the scene gallery",
                       f"Every scene at {RES}x{RES}, equal time ({budget:g} s per integrator); "
                       "each page flips between the reference and the integrators' images, with "
                       "exposure, zoom, false-colour error maps, every metric and its curves.",
                       [(name, f"{name}.html", _page_summary(result)) for name, result in results])
    return results


def _page_summary(result) -> str:
    """The index's line of a scene: each of ours, its efficiency against its built-in."""
    parts = [f"{r.integrator} {fmt_ratio(r.efficiency_ratio)}x" for r in result.rows
             if not r.builtin]
    return "(efficiency / built-in: " + ", ".join(parts) + ")" if parts else ""


# -- scale ------------------------------------------------------------------------------------
def smooth_grid(n: int, path: Path):
    """An n^3 density of three Gaussian puffs, built slab by slab (peak memory ~ the grid)."""
    import numpy as np
    x = (np.arange(n, dtype=np.float32) + 0.5) / n
    puffs = [((0.35, 0.4, 0.5), 0.12), ((0.65, 0.55, 0.45), 0.1), ((0.5, 0.3, 0.3), 0.08)]
    grid = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=(n, n, n))
    for k in range(n):                      # z slab k: axes (z, y, x)
        zz = x[k]
        slab = np.zeros((n, n), np.float32)
        for (cx, cy, cz), r in puffs:
            gy = np.exp(-((x - cy) ** 2) / (2 * r * r))
            gx = np.exp(-((x - cx) ** 2) / (2 * r * r))
            slab += np.exp(-((zz - cz) ** 2) / (2 * r * r)) * np.outer(gy, gx)
        grid[k] = slab
    grid.flush()
    del grid


def scale_worker(config: dict) -> dict:
    """One configuration in this (fresh) process: time and peak memory."""
    import mitsuba_plugins  # noqa: F401
    import drjit as dr
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    mi.set_log_level(mi.LogLevel.Error)     # multi-pass renders warn on every call
    integrator = {"type": config["integrator"], **config.get("params", {})}
    load_seconds = 0.0
    if "grid" in config:
        t0 = time.perf_counter()
        scene = mi.load_dict({
            "type": "scene",
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": 0.5}},
            "light": {"type": "sphere", "center": [1.5, 2.0, 1.5], "radius": 0.3,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 30.0}}},
            "box": {"type": "cube", "bsdf": {"type": "null"},
                    "interior": {"type": "grid_medium", "filename": config["grid"], "scale": 20.0,
                                 "albedo": 0.8, "to_world": mi.ScalarTransform4f().translate(
                                     [-1, -1, -1]).scale(2)}},
            "sensor": {"type": "perspective", "fov": 40,
                       "to_world": mi.ScalarTransform4f().look_at([0, 0.5, 4.5], [0, 0, 0], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": config["res"], "height": config["res"]}}})
        load_seconds = time.perf_counter() - t0
    else:
        scene = mi.load_file(str(ROOT / "scenes" / f"{config['scene']}.xml"), res=str(config["res"]))
    integ = mi.load_dict(integrator)
    times = []
    for k in range(4):                      # the first compiles
        t0 = time.perf_counter()
        img = mi.render(scene, integrator=integ, spp=config["spp"], seed=k)
        dr.eval(img)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    return {"render_s": statistics.median(times[1:]), "first_render_s": times[0],
            "load_s": load_seconds,
            "peak_rss_mb": status_mib("VmHWM")}


def scale(quick: bool, tmp: Path) -> list:
    configs = []
    sizes = (128, 256) if quick else (128, 256, 512, 1024)
    for res in sizes:
        configs.append({"axis": "image size", "scene": "cornell_box", "res": res, "spp": 16,
                        "integrator": "path_rr"})
    for spp in ((4, 16) if quick else (4, 16, 64, 256)):
        configs.append({"axis": "spp", "scene": "cornell_box", "res": 256, "spp": spp,
                        "integrator": "path_rr"})
    configs.append({"axis": "spp", "scene": "cornell_box", "res": 256, "spp": 256,
                    "integrator": "path_rr", "params": {"samples_per_pass": 16}})
    if not quick:
        for params in ({}, {"samples_per_pass": 16}):
            configs.append({"axis": "image size", "scene": "cornell_box", "res": 1024, "spp": 64,
                            "integrator": "path_rr", "params": params})
        configs.append({"axis": "spp", "scene": "cornell_box", "res": 256, "spp": 1024,
                        "integrator": "path_rr"})
    for n in ((64, 128) if quick else (64, 128, 256, 512)):
        grid = tmp / f"grid{n}.npy"
        smooth_grid(n, grid)
        configs.append({"axis": "grid resolution", "grid": str(grid), "n": n, "res": 128,
                        "spp": 16, "integrator": "volpath_delta", "params": {"max_depth": 16}})
    rows = []
    for config in configs:
        out = subprocess.run([sys.executable, "-m", __spec__.name,
                           "--scale-worker", json.dumps(config)],
                             capture_output=True, text=True, check=True, cwd=ROOT)
        line = next(x for x in reversed(out.stdout.splitlines()) if x.startswith('{"render_s"'))
        rows.append({**config, **json.loads(line)})
        print(f"scale {config['axis']}: {rows[-1]}", flush=True)
    return rows


# -- writing ----------------------------------------------------------------------------------
def fmt_ratio(x) -> str:
    return "-" if x is None or x != x else f"{x:.2f}"


def summary_table(results) -> str:
    """One line per (scene, one of ours): its efficiency and equal-time rel. MSE against
    the built-in, at equal time."""
    lines = ["| scene | ours | built-in | efficiency / built-in | rel. MSE / built-in (equal time) | FLIP (ours / built-in) | spp in the budget (ours / built-in) | NaN/Inf samples |",
             "|---|---|---|---|---|---|---|---|"]
    for name, result in results:
        for r in result.rows:
            if r.builtin:
                continue
            twin = next((b for b in result.rows if b.builtin and b.integrator.split(":")[0] ==
                         _twin_name(r.integrator)), None)
            lines.append(f"| {name} | `{r.integrator}` | `{twin.integrator if twin else '-'}` | "
                         f"{fmt_ratio(r.efficiency_ratio)} | {fmt_ratio(r.rel_mse_ratio)} | "
                         f"{r.flip:.4f} / {f'{twin.flip:.4f}' if twin else '-'} | "
                         f"{r.spp} / {twin.spp if twin else '-'} | "
                         f"{r.invalid + (twin.invalid if twin else 0)} |")
    return "\n".join(lines)


def _twin_name(label: str) -> str:
    from mitsuba_plugins.tools.integrator_specs import BUILTIN
    return BUILTIN[label.split(":")[0]]


def scale_table(rows) -> str:
    lines = ["| axis | configuration | render time [s] | first render [s] | grid load [s] | peak memory [MB] |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        what = (f"{r['n']}^3 grid, volpath_delta, {r['res']}^2 x {r['spp']} spp" if "n" in r else
                f"{r['scene']} {r['res']}^2 x {r['spp']} spp, {r['integrator']}")
        if r.get("params", {}).get("samples_per_pass"):
            what += f", samples_per_pass={r['params']['samples_per_pass']}"
        load = f"{r['load_s']:.2f}" if "n" in r else "-"
        lines.append(f"| {r['axis']} | {what} | {r['render_s']:.3f} | {r['first_render_s']:.2f} | "
                     f"{load} | {r['peak_rss_mb']:.0f} |")
    return "\n".join(lines)


def write_docs(results, scale_rows, meta) -> str:
    from mitsuba_plugins import output
    from mitsuba_plugins.tools import report
    summary = summary_table(results)
    parts = ["# Results", "",
             f"Generated by `python3 -m benchmarks.results` on {meta['date']} "
             f"({meta['cpu']}, {meta['cores']} cores, variant {meta['variant']}, Mitsuba "
             f"{meta['mitsuba']}, Dr.Jit {meta['drjit']}); the whole run took "
             f"{meta['minutes']:.1f} min from scratch.", "",
             f"Every scene at {RES}x{RES}, equal time: each integrator had {meta['budget']:g} s "
             "of rendering (16-spp passes, integrators taking turns, compilation excluded). "
             "rel. MSE is measured against a high-spp reference with the reference's own "
             "noise subtracted; efficiency = 1 / (rel. MSE x time). Ratios > 1 for efficiency "
             "and < 1 for rel. MSE favour ours. Media scenes are measured against a "
             "volpath_delta reference with other seeds (see each scene's legend).", "",
             f"Each scene also has an interactive page, all listed in "
             f"[{FIGURES.name}/index.html]({FIGURES.name}/index.html).", "",
             "## Summary", "", summary, "",
             f"![error against time, {HEADLINE}]({FIGURES.name}/{HEADLINE}_curves.png)", ""]
    for name, result in results:
        parts += [f"## {name}", "", f"Interactive page (flip between images, exposure, zoom, "
                  f"error maps; open the file in a browser): [{FIGURES.name}/{name}.html]"
                  f"({FIGURES.name}/{name}.html)", "", report.table(result, markdown=True), "",
                  "```", report.legend(result), "```", "",
                  f"![{name} curves]({FIGURES.name}/{name}_curves.png)", "",
                  f"![{name} panel]({FIGURES.name}/{name}_panel.png)", ""]
    if UNDERFLOW.exists():    # its own run (python3 -m benchmarks.underflow)
        body = UNDERFLOW.read_text().splitlines()
        parts += ["## Where volpath goes black (mitsuba3 #336)", "", *body[1:]]
        parts = [line.replace("../../docs/results/", f"{FIGURES.name}/") for line in parts]
    if scale_rows:
        parts += ["## Scale", "",
              "Each configuration in a fresh process; render time is the median of 3 renders "
              "after a first one (which traces the kernel; Dr.Jit's on-disk kernel cache "
              "usually spares the compilation); peak memory is the process's resident "
                  "high-water mark (Mitsuba and Dr.Jit themselves included); grid "
                  "load is scene loading with the grid file and its majorant grid.", "",
                  scale_table(scale_rows), "", SCALE_NOTE, ""]
    output.write_text(DOCS / f"{FIGURES.name}.md", "\n".join(parts))
    return summary


def update_readme(summary: str, meta) -> None:
    from mitsuba_plugins import output
    text = README.read_text()
    block = (f"{BEGIN}\n_Equal time, {meta['budget']:g} s per integrator at {RES}x{RES}, "
             f"{meta['cpu']} ({meta['cores']} cores), {meta['date']}; "
             "from `python3 -m benchmarks.results` (full tables, image panels and the scale "
             "table: [docs/results.md](docs/results.md)). Media scenes are measured against "
             "a volpath_delta reference with other seeds: it renders 10-20x the samples of "
             "volpath in the same time, the tests check it against volpath, and volpath is "
             "biased for chromatic media._\n\n"
             f"{summary}\n\n![error against time, {HEADLINE}](docs/results/{HEADLINE}_curves.png)\n{END}")
    if BEGIN in text:
        head, rest = text.split(BEGIN, 1)
        text = head + block + rest.split(END, 1)[1]
    else:
        text += "\n## Results\n\n" + block + "\n"
    output.write_text(README, text)


def main() -> int:
    from mitsuba_plugins import output
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--budget", type=float, default=10.0, help="seconds per integrator (10)")
    p.add_argument("--ref-seconds", type=float, default=60.0,
                   help="rendering time of each reference (60)")
    p.add_argument("--keep-references", action="store_true",
                   help="reuse references cached by a previous run")
    p.add_argument("--quick", action="store_true", help="tiny budgets; writes to a temp folder")
    p.add_argument("--only", nargs="*", help="gallery scenes to run")
    p.add_argument("--scale-worker", help=argparse.SUPPRESS)
    p.add_argument("--variant", default=None,
                   help="Mitsuba variant (default $MITSUBA_PLUGINS_VARIANT or llvm_ad_rgb)")
    p.add_argument("--no-scale", action="store_true", help="gallery only (no scale table)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="render missing references as tasks on this Dask cluster; the timed "
                        "cells run here, one at a time")
    p.add_argument("--cells", action="store_true",
                   help="with --scheduler: run each scene's whole cell (references and timed "
                        "rows) as one task; start one worker per machine (dask worker "
                        "--nworkers 1) so that timed cells never share a machine")
    args = p.parse_args()
    if args.scale_worker:
        print(json.dumps(scale_worker(json.loads(args.scale_worker))))
        return 0

    import mitsuba_plugins  # noqa: F401
    import drjit as dr
    import mitsuba as mi
    from mitsuba_plugins.registry import default_variant
    variant = args.variant or default_variant()
    mi.set_variant(variant)
    os.chdir(ROOT)
    global DOCS, FIGURES, README
    if variant != "llvm_ad_rgb":
        FIGURES, README = DOCS / f"results_{variant}", None
    if args.quick:
        args.budget, args.ref_seconds = 0.5, 2.0
        DOCS = Path(tempfile.mkdtemp(prefix="results-quick-"))
        FIGURES = DOCS / FIGURES.name
        if README is not None:
            README = DOCS / "README.md"
            README.write_text("")
    FIGURES.mkdir(parents=True, exist_ok=True)
    cache = ROOT / ".cache" / "results-references"
    if not args.keep_references and cache.exists():
        shutil.rmtree(cache)
    start = time.perf_counter()
    if args.cells and not args.scheduler:
        p.error("--cells needs --scheduler")
    results = gallery(args.budget, args.ref_seconds, cache, args.only, args.scheduler, args.cells)
    scale_rows = []
    if not args.no_scale:
        with tempfile.TemporaryDirectory() as tmp:
            scale_rows = scale(args.quick, Path(tmp))
    meta = {"date": datetime.date.today().isoformat(), "cpu": device_model(variant),
            "variant": variant,
            "cores": os.cpu_count(), "mitsuba": mi.__version__, "drjit": dr.__version__,
            "budget": args.budget, "minutes": (time.perf_counter() - start) / 60}
    summary = write_docs(results, scale_rows, meta)
    if README is not None:
        update_readme(summary, meta)
    if scale_rows:
        output.write_json(FIGURES / "scale.json", scale_rows, indent=1)
    print(f"wrote {DOCS / (FIGURES.name + '.md')}{' and the README summary' if README else ''} "
          f"in {meta['minutes']:.1f} min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
