"""Guiding in volumes on the dense family at equal spp: ``volpath_delta`` with ``guiding =
volumes`` against ``volpath_delta`` unguided, both at ``--spp`` (256) on the family of
``benchmarks/dense_heldout.py`` at 32x32, where a render of 256 spp has exactly the
training paths that ``guided_render.MIN_TRAINING_PATHS`` asks for and is guided.

Per scene: a 4096-spp reference of ``dense.REFERENCE``; 6 renders of each configuration,
alternating; time = the median of the last 5 (the first compiles), relMSE = the mean
over the 6 of ``stats.rel_mse`` (the reference's own noise is left in, which pulls both
ratios toward 1 a little); medium vertices per camera
ray from a 4-spp plain render (``instrument.counting``); the guided render's first-pass
share (``GuidingReport.share``) and whether it went on unguided.

``python3 -m benchmarks.guiding_dense_equal_spp --half tuning`` (or ``test``) writes
``benchmarks/results/guiding_dense_equal_spp_<half>.{json,md}``; ``--markdown`` only
rewrites the tables from the JSON files.
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from benchmarks import dense_heldout as dh
import mitsuba as mi
import numpy as np

from mitsuba_plugins import output
from mitsuba_plugins.instrument import counting
from mitsuba_plugins.tools import stats

ROOT = Path(__file__).resolve().parents[1]
RES, REF_SPP, RUNS = 32, 4096, 6


def measure(case, spp: int, tmp: Path) -> dict:
    sc = dh.scene(case, RES, tmp)
    plain = mi.load_dict({"type": "volpath_delta"})
    with counting() as n:
        mi.render(sc, integrator=mi.load_dict({"type": "volpath_delta"}), spp=4, seed=5)
        vpp = n["medium_vertices"] / (RES * RES * 4)
    ref = np.array(mi.render(sc, integrator=mi.load_dict(dict(dh.dense.REFERENCE)),
                             spp=REF_SPP, seed=99))[..., :3]
    row = {}
    guided = mi.load_dict({"type": "volpath_delta", "guiding": "volumes"})
    for k in range(RUNS):
        for name, integ in (("plain", plain), ("guided", guided)):
            t0 = time.perf_counter()
            im = np.array(mi.render(sc, integrator=integ, spp=spp, seed=k))[..., :3]
            t = time.perf_counter() - t0
            r = row.setdefault(name, {"t": [], "e": []})
            r["t"].append(t)
            r["e"].append(stats.rel_mse(im, ref))
    tp, tg = np.median(row["plain"]["t"][1:]), np.median(row["guided"]["t"][1:])
    ep, eg = np.mean(row["plain"]["e"]), np.mean(row["guided"]["e"])
    rep = guided.guiding_report
    return dict(vpp=float(vpp), time_ratio=float(tg / tp), var_ratio=float(eg / ep),
                eff=float((tp * ep) / (tg * eg)), share=float(rep.share),
                skipped=bool(rep.skipped))


def markdown(half: str, rows: dict, spp: int = 256) -> str:
    effs = [r["eff"] for r in rows.values()]
    lines = [f"# Guiding in volumes on the dense family's {half} half at equal spp", "",
             f"`python3 -m benchmarks.guiding_dense_equal_spp --half {half}` (docstring: the "
             f"method): {RES}x{RES}, {spp} spp, guided over unguided `volpath_delta`.", "",
             "| scene | medium vertices per camera ray | first-pass share | time | relMSE "
             "| efficiency |", "|---|---|---|---|---|---|"]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['vpp']:.1f} | {r['share']:.2f}"
                     f"{' (skipped)' if r['skipped'] else ''} | {r['time_ratio']:.2f} | "
                     f"{r['var_ratio']:.2f} | {r['eff']:.2f} |")
    lines += ["", f"Efficiency: median {statistics.median(effs):.2f}, "
              f"{min(effs):.2f}-{max(effs):.2f}.", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--half", choices=("tuning", "test"), default="tuning")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--markdown", action="store_true", help="only rewrite the .md")
    args = ap.parse_args()
    out = ROOT / "benchmarks" / "results" / f"guiding_dense_equal_spp_{args.half}"
    if args.markdown:
        rows = json.loads(out.with_suffix(".json").read_text())
    else:
        rows = {}
        with tempfile.TemporaryDirectory() as tmp:
            for case in (c for c in dh.family() if c.half == args.half):
                rows[case.name] = measure(case, args.spp, Path(tmp))
                print(case.name, rows[case.name], flush=True)
                output.write_json(out.with_suffix(".json"), rows, indent=1)
    output.write_text(out.with_suffix(".md"), markdown(args.half, rows, args.spp))
    print(markdown(args.half, rows, args.spp))


if __name__ == "__main__":
    main()
