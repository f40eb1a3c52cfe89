"""Command line: ``mitsuba-plugins render``, ``compare`` and ``grid``.

Errors reach the user as one line: Mitsuba wraps a plugin's exception in a parser error
whose text embeds the Python traceback, so the last ``...Error: message`` line is shown.

Every option is checked, and every output path is checked (:mod:`mitsuba_plugins.output`),
before any work starts; outputs are written to a temporary name and renamed when complete.
The command runs in a worker thread while the main thread waits for it, so Ctrl-C is
answered within a fraction of a second even while a render kernel runs (a kernel cannot
be stopped from Python): the process then removes its unfinished temporary files, prints
``mitsuba-plugins: interrupted`` and exits with status 130, wherever it was.
"""
from __future__ import annotations

import argparse
import math
import os
import re
import sys
import threading
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
from mitsuba_plugins import output

#: exit status of an interrupted command (128 + SIGINT), as shells report it
EXIT_INTERRUPTED = 130
#: largest seed: Mitsuba's samplers take an unsigned 32-bit seed
MAX_SEED = 2 ** 32 - 1
#: longest --time-budget per integrator (a week): a larger one is a typo, not a plan
MAX_TIME_BUDGET = 7 * 24 * 3600.0

_ERROR_LINE = re.compile(r"^\s*(?:[\w.]+\.)?(\w*(?:Error|Exception)): (.+)$")


def user_message(error: BaseException) -> str:
    """One clear line for ``error``, unwrapping Mitsuba's plugin-instantiation errors."""
    while error.__cause__ is not None:
        error = error.__cause__
    text = str(error)
    for line in reversed(text.splitlines()):
        m = _ERROR_LINE.match(line)
        if m:
            return m.group(2).strip()
    return text.splitlines()[-1].strip() if text.strip() else type(error).__name__


def render_target(args) -> Path:
    return Path(args.output or Path("out") / f"{Path(args.scene).stem}.exr")


def warn_if_ignored(scene, integrator_type: str, scene_path) -> None:
    """Say on stderr when the integrator leaves part of the scene out (a built-in on an
    emissive medium, a surface integrator on media)."""
    from mitsuba_plugins.tools.integrator_specs import ignores
    missing = ignores(scene, integrator_type)
    if missing:
        print(f"mitsuba-plugins: warning: this integrator ignores the {missing} of "
              f"{scene_path}; render it with volpath_delta or volpath_raymarch",
              file=sys.stderr, flush=True)


def cmd_render(args) -> int:
    import mitsuba as mi
    from mitsuba_plugins.tools.integrator_specs import parse_integrator, plugin_name
    from mitsuba_plugins.tools.scenes import load_scene
    from mitsuba_plugins.tools.stats import timed_pass
    from mitsuba_plugins.validity import counted
    out = render_target(args)
    scene = load_scene(args.scene, args.res)
    integrator = counted(mi.load_dict(parse_integrator(args.integrator)) if args.integrator
                         else scene.integrator())
    warn_if_ignored(scene, plugin_name(integrator.inner if hasattr(integrator, "inner")
                                       else integrator), args.scene)
    print(f"rendering {args.scene} ...", file=sys.stderr, flush=True)
    seconds, array, invalid = timed_pass(scene, integrator, args.spp or 0, args.seed)
    output.write_exr(out, array)
    output.write_png(out.with_suffix(".png"), array)  # sRGB tone map, clamped
    print(f"wrote {out} and {out.with_suffix('.png')} ({seconds:.2f} s including compilation; "
          f"{invalid} NaN/Inf samples, zeroed)")
    return 1 if invalid else 0


def compare_folder(args) -> Path:
    return Path(args.output or Path("out") / "compare" / Path(args.scene).stem)


def cmd_compare(args) -> int:
    from mitsuba_plugins.tools import report as rep
    from mitsuba_plugins.tools.compare import compare
    from mitsuba_plugins.tools.integrator_specs import parse_integrator
    integrators = [parse_integrator(s) for s in args.integrators.split(",") if s.strip()]
    result = compare(args.scene, integrators, spp=args.spp, passes=args.passes,
                     time_budget=args.time_budget, spp_per_pass=args.spp_per_pass,
                     ref_spp=args.ref_spp, res=args.res, cache_dir=Path(args.cache),
                     seed=args.seed, progress=not args.quiet,
                     reference=parse_integrator(args.reference) if args.reference else None,
                     scheduler=args.scheduler)
    out = compare_folder(args)
    written = rep.write_all(result, out)
    print()
    print(rep.table(result))
    print()
    print(rep.legend(result))
    invalid = sum(r.invalid for r in result.rows)
    print(f"NaN/Inf samples: {invalid} (counted in every integrator's kernel, zeroed in the images)")
    print(f"written to {out}/: table.md, table.csv, results.json, curves.png, panel.png, images")
    print(f"report (open in a browser, works offline): {written['page']}")
    return 1 if invalid else 0


def reference_folder(args) -> Path:
    return Path(args.output or Path("out") / "reference" / Path(args.scene).stem)


def cmd_reference(args) -> int:
    import mitsuba as mi
    from mitsuba_plugins.tools.integrator_specs import parse_integrator
    from mitsuba_plugins.tools.scenes import load_scene
    from mitsuba_plugins.tools.reference import reference
    folder = reference_folder(args)
    integrator = parse_integrator(args.integrator)
    # the scene and the integrator's parameters are checked here, once, before any
    # worker starts (a bad one raised in every task, each with Dask's traceback)
    scene = load_scene(args.scene, args.res)
    mi.load_dict(integrator)
    warn_if_ignored(scene, integrator["type"], args.scene)
    info = reference(args.scene, integrator, args.spp, args.passes,
                     folder, res=args.res, seed=args.seed, workers=args.workers,
                     scheduler=args.scheduler, threads=args.threads, variant=args.variant,
                     progress=not args.quiet)
    workers = sorted({p["worker"] for p in info["per_pass"]})
    print(f"wrote {folder / 'mean.exr'}, stderr.exr and reference.json: {info['spp']} spp in "
          f"{info['passes']} passes ({info['resumed_passes']} kept from an earlier run) on "
          f"{len(workers)} worker(s), {info['wall_seconds']:.1f} s; {info['invalid']} NaN/Inf "
          "samples")
    return 1 if info["invalid"] else 0


def cmd_grid_info(args) -> int:
    """Every file is reported, readable or not; the status is 1 if any is invalid or
    unreadable (each named on its own line)."""
    from mitsuba_plugins.grids.gridio import GridFileError
    from mitsuba_plugins.tools import grid_info
    invalid = 0
    for path in args.files:
        try:
            info = grid_info.grid_info(path, args.majorant_resolution, args.grid)
        except GridFileError as error:
            print(f"mitsuba-plugins: error: {user_message(error)}", file=sys.stderr,
                  flush=True)
            invalid += 1
            continue
        if args.json:
            info["null_means"] = output.JSON_NULL_MEANS
            print(output.dumps_json(info, indent=2), flush=True)
        else:
            print(grid_info.format_info(info), flush=True)
        invalid += bool(info.get("nonfinite") or info.get("negative"))
    if invalid:
        print(f"mitsuba-plugins: error: {invalid} of {len(args.files)} grid file(s) invalid "
              "or unreadable (see above); grid_medium refuses them", file=sys.stderr)
    return 1 if invalid else 0


def cmd_grid_convert(args) -> int:
    from mitsuba_plugins.grids import gridio
    gridio.convert(args.source, args.target, args.grid,
                   report=lambda line: print(line, flush=True))
    print(f"wrote {args.target}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mitsuba-plugins", description=__doc__.splitlines()[0])
    from mitsuba_plugins.registry import VARIANT_VARIABLE, default_variant
    p.add_argument("--variant", default=default_variant(),
                   help=f"Mitsuba variant (default ${VARIANT_VARIABLE} or llvm_ad_rgb)")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render a scene to EXR (+ PNG preview)")
    r.add_argument("scene")
    r.add_argument("-i", "--integrator", help="e.g. path_rr or path_rr:max_depth=5 (default: the scene's)")
    r.add_argument("--spp", type=int, help="samples per pixel (default: the scene's)")
    r.add_argument("--res", type=int, help="image width/height, for scenes with a $res parameter")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("-o", "--output", help="output .exr (default out/SCENE.exr)")
    r.set_defaults(func=cmd_render)

    c = sub.add_parser("compare", help="time, relative MSE and efficiency against a reference")
    c.add_argument("scene")
    c.add_argument("-i", "--integrators", required=True,
                   help="comma-separated, e.g. direct_mis,direct,path_rr:max_depth=5,path:max_depth=5")
    c.add_argument("--spp", type=int, default=64,
                   help="equal-spp mode: samples per pixel of each integrator (default 64)")
    c.add_argument("--passes", type=int, default=4,
                   help="equal-spp mode: timed passes the spp are split into (default 4)")
    c.add_argument("--time-budget", type=float, metavar="SECONDS",
                   help="equal-time mode: each integrator renders passes until it has spent "
                        "SECONDS (compilation excluded)")
    c.add_argument("--spp-per-pass", type=int,
                   help="samples per pass (default: spp / passes; 16 with --time-budget)")
    c.add_argument("--ref-spp", type=int,
                   help="reference spp (default max(1024, 16 x spp); 4096 with --time-budget)")
    c.add_argument("--reference", metavar="INTEGRATOR",
                   help="reference for all (default: each one's built-in counterpart), e.g. "
                        "volpath_delta where volpath is biased")
    c.add_argument("--res", type=int, help="image width/height, for scenes with a $res parameter")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--cache", default=".cache/references", help="reference cache folder")
    c.add_argument("--scheduler", metavar="ADDRESS",
                   help="render missing references as tasks on this Dask cluster (the timed "
                        "rows run here)")
    c.add_argument("-o", "--output", help="output folder (default out/compare/SCENE)")
    c.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    c.set_defaults(func=cmd_compare)

    rf = sub.add_parser("reference", help="render a high-spp reference, each pass a Dask task "
                                          "(mean.exr, stderr.exr, reference.json)")
    rf.add_argument("scene")
    rf.add_argument("-i", "--integrator", required=True,
                    help="e.g. volpath_delta or path:max_depth=5")
    rf.add_argument("--spp", type=int, required=True, help="total samples per pixel")
    rf.add_argument("--passes", type=int, default=16,
                    help="passes (tasks) the spp are split into; seeds seed + pass (default 16)")
    rf.add_argument("--res", type=int, help="image width/height, for scenes with a $res parameter")
    rf.add_argument("--seed", type=int, default=0)
    where = rf.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int,
                       help="local worker processes, each with cores / workers Dr.Jit "
                            "threads (default 1: one process using every core)")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="an existing Dask scheduler, e.g. tcp://10.0.0.1:8786")
    rf.add_argument("--threads", type=int,
                    help="Dr.Jit threads per worker (default: cores / workers locally, all "
                         "cores with --scheduler)")
    rf.add_argument("-o", "--output", help="output folder (default out/reference/SCENE)")
    rf.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    rf.set_defaults(func=cmd_reference)

    g = sub.add_parser("grid", help="inspect density grids (.vol, .npy, .vdb)")
    gsub = g.add_subparsers(dest="grid_command", required=True)
    gi = gsub.add_parser("info", help="shape, bounds, density statistics, majorant-grid "
                                      "emptiness")
    gi.add_argument("files", nargs="+", help=".vol, .npy or .vdb grid files")
    gi.add_argument("--grid", help="which grid of a .vdb file to read: a name, or name[K] for "
                                   "the K-th of several of one name (default density, if "
                                   "there is exactly one); all are listed")
    gi.add_argument("--majorant-resolution", type=int, default=16,
                    help="majorant cells per axis, in [1, 1024] (default 16)")
    gi.add_argument("--json", action="store_true", help="print JSON")
    gi.set_defaults(func=cmd_grid_info)
    gc = gsub.add_parser("convert", help="convert a grid (.vol, .npy, .vdb) to .vol, .npy "
                                         "(dense; the size is printed first) or .vdb")
    gc.add_argument("source", help=".vol, .npy or .vdb grid file")
    gc.add_argument("target", help=".vol (keeps the world box), .npy, or .vdb (keeps the "
                                   "placement; zeros stay inactive)")
    gc.add_argument("--grid", default="density",
                    help="which grid of a .vdb to read (a name, or name[K] for the K-th of "
                         "several of one name), and the name of the grid written to a .vdb "
                         "(default density)")
    gc.set_defaults(func=cmd_grid_convert)
    return p


#: largest --res: a 16384^2 film of 4 channels still indexes below 2^32 (Dr.Jit's
#: array index; 100000 failed inside Mitsuba with "Tensor(): invalid size specified")
MAX_RES = 16384
#: largest --spp: Mitsuba's sample count is a 32-bit unsigned integer
MAX_SPP = 2 ** 32 - 1


class OptionError(ValueError):
    """A command-line option out of its range."""


def _int_range(args, name: str, lo: int, hi: int | None = None):
    value = getattr(args, name.lstrip("-").replace("-", "_"), None)
    if value is not None and (value < lo or (hi is not None and value > hi)):
        allowed = f"an integer in [{lo}, {hi}]" if hi is not None else f"an integer >= {lo}"
        raise OptionError(f"{name} = {value} is invalid; allowed: {allowed}")


def check_options(args) -> None:
    """Every option in range, and every output writable, before any work starts."""
    if args.command in ("render", "compare", "reference"):
        _int_range(args, "--res", 1, MAX_RES)
        _int_range(args, "--spp", 1, MAX_SPP)
        _int_range(args, "--seed", 0, MAX_SEED)
    if args.command == "render":
        out = render_target(args)
        output.check_targets([out], extensions=(".exr",), option="-o/--output")
        output.check_targets([out.with_suffix(".png")], option="-o/--output (PNG preview)")
    elif args.command == "compare":
        _int_range(args, "--passes", 1)
        _int_range(args, "--spp-per-pass", 1)
        _int_range(args, "--ref-spp", 1, MAX_SPP)
        if args.time_budget is None and args.spp_per_pass is None and args.passes and \
                args.spp and args.spp >= args.passes and args.spp % args.passes:
            raise OptionError(f"--spp = {args.spp} is invalid; allowed: a multiple of "
                              f"--passes ({args.passes})")
        budget = args.time_budget
        if budget is not None and not (math.isfinite(budget) and 0 < budget <= MAX_TIME_BUDGET):
            raise OptionError(f"--time-budget = {budget} is invalid; allowed: a number of "
                              f"seconds in (0, {MAX_TIME_BUDGET:g}]")
        from mitsuba_plugins.tools import report as rep
        from mitsuba_plugins.tools.integrator_specs import label, parse_integrator
        labels = [label(parse_integrator(s)) for s in args.integrators.split(",") if s.strip()]
        twice = sorted({name for name in labels if labels.count(name) > 1})
        if twice:
            raise OptionError(f"-i lists {', '.join(repr(n) for n in twice)} more than once; "
                              "allowed: each integrator (with its parameters) once")
        folder = compare_folder(args)
        output.check_folder_target(folder, option="-o/--output")
        output.check_targets([folder / name for name in rep.output_names(labels)],
                             option="-o/--output")
        rep.check_not_foreign(folder, rep.output_names(labels))
        output.check_folder_target(args.cache, option="--cache")
    elif args.command == "reference":
        _int_range(args, "--passes", 1)
        _int_range(args, "--workers", 1, os.cpu_count() or 1)
        _int_range(args, "--threads", 1)
        if args.spp % args.passes:
            raise OptionError(f"--spp = {args.spp} is invalid; allowed: a multiple of "
                              f"--passes ({args.passes})")
        output.check_folder_target(reference_folder(args), option="-o/--output")
    if args.command in ("compare", "reference") and args.scheduler is not None:
        from mitsuba_plugins.tools.reference import ReferenceError, check_scheduler
        try:
            check_scheduler(args.scheduler)
        except ReferenceError as error:
            raise OptionError(str(error)) from None
    elif args.command == "grid" and args.grid_command == "info":
        _int_range(args, "--majorant-resolution", 1, 1024)
    # grid convert checks its target itself (gridio.convert), before it reads anything


def _run(args, result: dict) -> None:
    """The command, in the worker thread; its exit status or error goes to ``result``."""
    try:
        import mitsuba as mi
        mi.set_variant(args.variant)
        result["rc"] = args.func(args)
    except BaseException as error:  # handed to the main thread
        result["error"] = error


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        check_options(args)
    except ValueError as error:   # OptionError, OutputError, a bad integrator spec
        print(f"mitsuba-plugins: error: {user_message(error)}", file=sys.stderr)
        return 2
    result = {}
    worker = threading.Thread(target=_run, args=(args, result), name="mitsuba-plugins",
                              daemon=True)
    try:
        worker.start()
        while worker.is_alive():
            worker.join(0.05)
    except KeyboardInterrupt:
        interrupted()
    error = result.get("error")
    if error is None:
        return result.get("rc", 0)
    if isinstance(error, KeyboardInterrupt):
        interrupted()
    # one clear line, not a Dr.Jit traceback
    print(f"mitsuba-plugins: error: {user_message(error)}", file=sys.stderr)
    return 2


def interrupted():
    """Ctrl-C: no half-written file stays behind; the same message and status wherever
    it came. The process exits at once, since a running kernel cannot be stopped."""
    output.remove_pending()
    if "mitsuba_plugins.tools.reference" in sys.modules:
        sys.modules["mitsuba_plugins.tools.reference"].shutdown()
    print("mitsuba-plugins: interrupted", file=sys.stderr, flush=True)
    sys.stdout.flush()
    os._exit(EXIT_INTERRUPTED)


if __name__ == "__main__":
    sys.exit(main())
