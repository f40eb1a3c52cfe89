"""Command line: ``mitsuba-plugins render`` and ``mitsuba-plugins compare``.

Errors reach the user as one line: Mitsuba wraps a plugin's exception in a parser error
whose text embeds the Python traceback, so the last ``...Error: message`` line is shown.
"""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads

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


def _write_outputs(image, exr: Path):
    import mitsuba as mi
    import numpy as np
    exr.parent.mkdir(parents=True, exist_ok=True)
    bitmap = mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32))
    bitmap.write(str(exr))
    mi.util.write_bitmap(str(exr.with_suffix(".png")), bitmap)  # sRGB tone map, clamped


def cmd_render(args) -> int:
    import mitsuba as mi
    from mitsuba_plugins.compare import load_scene, parse_integrator
    from mitsuba_plugins.stats import timed_pass
    from mitsuba_plugins.validity import counted
    scene = load_scene(args.scene, args.res)
    integrator = counted(mi.load_dict(parse_integrator(args.integrator)) if args.integrator
                         else scene.integrator())
    seconds, array, invalid = timed_pass(scene, integrator, args.spp or 0, args.seed)
    out = Path(args.output or Path("out") / f"{Path(args.scene).stem}.exr")
    _write_outputs(array, out)
    print(f"wrote {out} and {out.with_suffix('.png')} ({seconds:.2f} s including compilation; "
          f"{invalid} NaN/Inf samples, zeroed)")
    return 1 if invalid else 0


def cmd_compare(args) -> int:
    from mitsuba_plugins import report as rep
    from mitsuba_plugins.compare import compare, parse_integrator
    integrators = [parse_integrator(s) for s in args.integrators.split(",") if s.strip()]
    result = compare(args.scene, integrators, spp=args.spp, passes=args.passes,
                     time_budget=args.time_budget, spp_per_pass=args.spp_per_pass,
                     ref_spp=args.ref_spp, res=args.res, cache_dir=Path(args.cache),
                     seed=args.seed, progress=not args.quiet,
                     reference=parse_integrator(args.reference) if args.reference else None)
    out = Path(args.output or Path("out") / "compare" / Path(args.scene).stem)
    rep.write_all(result, out)
    print()
    print(rep.table(result))
    print()
    print(rep.legend(result))
    invalid = sum(r.invalid for r in result.rows)
    print(f"NaN/Inf samples: {invalid} (counted in every integrator's kernel, zeroed in the images)")
    print(f"written to {out}/: table.md, table.csv, results.json, curves.png, panel.png, images")
    return 1 if invalid else 0


def cmd_grid_info(args) -> int:
    import json
    from mitsuba_plugins import gridio
    for path in args.files:
        info = gridio.grid_info(path, args.majorant_resolution)
        print(json.dumps(info, indent=2) if args.json else gridio.format_info(info))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mitsuba-plugins", description=__doc__.splitlines()[0])
    p.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (default llvm_ad_rgb)")
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
    c.add_argument("-o", "--output", help="output folder (default out/compare/SCENE)")
    c.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    c.set_defaults(func=cmd_compare)

    g = sub.add_parser("grid", help="inspect density grids (.vol, .npy)")
    gsub = g.add_subparsers(dest="grid_command", required=True)
    gi = gsub.add_parser("info", help="shape, bounds, density statistics, majorant-grid "
                                      "emptiness")
    gi.add_argument("files", nargs="+", help=".vol or .npy grid files")
    gi.add_argument("--majorant-resolution", type=int, default=16,
                    help="majorant cells per axis (default 16)")
    gi.add_argument("--json", action="store_true", help="print JSON")
    gi.set_defaults(func=cmd_grid_info)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        import mitsuba as mi
        mi.set_variant(args.variant)
        if args.command == "render" and args.spp is not None and args.spp <= 0:
            raise ValueError(f"--spp must be >= 1; got {args.spp}")
        return args.func(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as error:  # one clear line, not a Dr.Jit traceback
        print(f"mitsuba-plugins: error: {user_message(error)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
