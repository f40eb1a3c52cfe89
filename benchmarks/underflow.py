"""Where Mitsuba's volpath goes black on production density (mitsuba3 issue #336).

A dense procedural cloud (benchmarks/cloud.py, 128^3, about 4% active, largest extinction
``--sigma``) stored as a ``.vol`` whose box is the cloud's active box, inside a bounding
cube [-1, 1]^3 with a null BSDF, as users wrap a grid, under sun and sky. Where a ray
crosses the cube but not the grid's box, volpath weighs its free flight by
exp(-majorant t) / exp(-majorant t) over the whole chord t: 0 / 0 once majorant x t
passes ~87, and the path is dropped. Measured:

* volpath and volpath_delta on that scene (Mitsuba's ``heterogeneous`` + ``gridvolume``,
  what the user has), and volpath_delta with ``grid_medium`` on the same ``.vol``;
* the reference: volpath where it is right, the cube fitted to the grid's box (null
  interfaces are invisible, so the radiance is the same), at ``--ref-spp``;
* per image: the fraction of pixels exactly 0 where the reference is not, the image mean
  against the reference's, and the relative MSE.

Writes ``benchmarks/results/underflow.{md,json}`` and ``docs/results/underflow_panel.png``
(the gallery, ``benchmarks/results.py``, includes the table).

    python3 -m benchmarks.underflow                 # about 5 minutes on 2 cores
"""
from __future__ import annotations

import argparse
import datetime
import json
import sys
import tempfile
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import mitsuba as mi
import numpy as np

from benchmarks.cloud import cloud_slices, extent
from benchmarks.harness import cpu_model

ROOT = Path(__file__).resolve().parents[1]


def T():
    return mi.ScalarTransform4f()


def write_cloud(n: int, path: Path) -> tuple:
    """The cloud's active box as a .vol (values normalised to a maximum of 1); returns the
    box's world corners (the cube [-1, 1]^3 holds the whole n^3 index box)."""
    from mitsuba_plugins.grids import gridio
    lo, hi = extent(n)
    data = np.zeros((hi - lo,) * 3, np.float32)
    for k, d in cloud_slices(n):
        data[k - lo] = d
    data /= data.max()
    box = (tuple([2.0 * lo / n - 1.0] * 3), tuple([2.0 * hi / n - 1.0] * 3))
    gridio.write_vol(path, data, bbox=box)
    return box


def scene(vol: Path, box, sigma: float, medium: str, fitted: bool, res: int) -> mi.Scene:
    volume = {"type": "gridvolume", "filename": str(vol), "use_grid_bbox": True}
    media = {"heterogeneous": {"type": "heterogeneous", "sigma_t": volume},
             "grid_medium": {"type": "grid_medium", "filename": str(vol),
                             "use_grid_bbox": True}}
    m = {**media[medium], "scale": sigma, "albedo": 0.95,
         "phase": {"type": "hg", "g": 0.5}}
    lo, hi = np.array(box[0]), np.array(box[1])
    cube = T().translate((lo + hi) / 2).scale((hi - lo) / 2) if fitted else T()
    return mi.load_dict({
        "type": "scene",
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.35, 0.45, 0.6]}},
        "sun": {"type": "directional", "direction": [-1, -1, -0.5],
                "irradiance": {"type": "rgb", "value": 3.0}},
        "cube": {"type": "cube", "to_world": cube, "bsdf": {"type": "null"}, "interior": m},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at([0, 0.5, 4.2], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}}})


def render(sc, integrator: str, spp: int, seed: int) -> np.ndarray:
    spec = {"type": integrator, "max_depth": 64}
    return np.array(mi.render(sc, integrator=mi.load_dict(spec), spp=spp, seed=seed),
                    dtype=np.float64)


def measure(img: np.ndarray, ref: np.ndarray) -> dict:
    lum_ref, lum = ref.mean(axis=2), img.mean(axis=2)
    lit = lum_ref > 1e-3
    rel = (img - ref) ** 2 / (ref ** 2 + 1e-2)
    return {"black_fraction": float(np.mean((lum == 0) & lit)),
            "mean": float(lum.mean()), "mean_ratio": float(lum.mean() / lum_ref.mean()),
            "rel_mse": float(rel.mean()), "nonfinite": int(np.sum(~np.isfinite(img)))}


def panel(images: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(images) + 1, figsize=(3 * (len(images) + 1), 3.3))
    tone = lambda x: np.clip(x / (1 + x), 0, 1) ** (1 / 2.2)  # noqa: E731
    for ax, (label, img) in zip(axes, images.items()):
        ax.imshow(tone(img)), ax.set_title(label, fontsize=8), ax.axis("off")
    volpath = images["volpath (heterogeneous)"]
    axes[-1].imshow(volpath.mean(axis=2) == 0, cmap="gray_r")
    axes[-1].set_title("volpath's pixels exactly 0", fontsize=8)
    axes[-1].axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--sigma", type=float, default=200.0,
                    help="largest extinction of the cloud (per unit length)")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    args = ap.parse_args()
    mi.set_variant(args.variant)
    mi.set_log_level(mi.LogLevel.Error)
    with tempfile.TemporaryDirectory() as tmp:
        vol = Path(tmp) / "cloud.vol"
        box = write_cloud(128, vol)
        ref = render(scene(vol, box, args.sigma, "heterogeneous", True, args.res), "volpath",
                     args.ref_spp, 7)
        runs = {"volpath (heterogeneous)": ("heterogeneous", "volpath"),
                "volpath_delta (heterogeneous)": ("heterogeneous", "volpath_delta"),
                "volpath_delta (grid_medium)": ("grid_medium", "volpath_delta")}
        images = {"reference: volpath, cube fitted": ref}
        rows = {}
        for label, (medium, integrator) in runs.items():
            images[label] = render(scene(vol, box, args.sigma, medium, False, args.res),
                                   integrator, args.spp, 1)
            rows[label] = measure(images[label], ref)
    depth = args.sigma * 2 * np.sqrt(3) * (1 - (box[1][0] - box[0][0]) / 2)
    result = {"date": datetime.date.today().isoformat(), "cpu": cpu_model(),
              "variant": args.variant, "mitsuba": mi.__version__, "res": args.res,
              "spp": args.spp, "ref_spp": args.ref_spp, "sigma": args.sigma,
              "grid_box": box, "rows": rows}
    out = ROOT / "benchmarks" / "results" / "underflow"
    out.with_suffix(".json").write_text(json.dumps(result, indent=1))
    figure = ROOT / "docs" / "results" / "underflow_panel.png"
    panel(images, figure)
    lines = [
        "# Where Mitsuba's volpath goes black (mitsuba3 #336)", "",
        f"Measured {result['date']} on {result['cpu']} ({args.variant}, Mitsuba "
        f"{result['mitsuba']}) by `python3 -m benchmarks.underflow`: a procedural cloud "
        f"(128^3, about 4% active, largest extinction {args.sigma:g}, albedo 0.95, HG 0.5) "
        "stored as a .vol whose box is the cloud's active box, inside a bounding cube "
        "[-1, 1]^3 with a null BSDF, sun and sky; "
        f"{args.res}x{args.res}, {args.spp} spp. Reference: volpath with the cube fitted "
        f"to the grid's box (where it is right), {args.ref_spp} spp. The majorant's "
        f"optical depth across the empty corners of the cube reaches about {depth:.0f}, "
        "past float32's exp(-87).", "",
        "| integrator (medium) | pixels exactly 0 (reference lit) | image mean / "
        "reference's | rel. MSE | NaN/Inf pixels |", "|---|---|---|---|---|"]
    for label, r in rows.items():
        lines.append(f"| {label} | {r['black_fraction']:.2%} | {r['mean_ratio']:.4f} | "
                     f"{r['rel_mse']:.3g} | {r['nonfinite']} |")
    lines += ["", "![underflow panel](../../docs/results/underflow_panel.png)", ""]
    out.with_suffix(".md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
