"""The sparse single-scattering block of tests/integrators/test_volpath_raymarch.py, measured.

``test_single_against_volpath_depth_2[sparse_grid_medium]`` compares ``volpath_raymarch``
``single`` (8 passes x 32 spp, seeds 1000-1007) with ``volpath`` at ``max_depth = 2``
(16 x 64 spp, seeds 0-15) on ``scenes/sparse.xml`` at 32x32. One 8x8 block (rows and
columns 8-15, blue) differed by t = -3.4 (-3.7 at the z critical values used before
the Welch degrees of freedom). This script renders that block alone (a film crop) with
many more samples, to decide whether ours or the reference is off:

* ``volpath_raymarch`` (the test's settings), ``volpath`` and ``volpath_delta`` at high
  spp, each as independent passes: the block mean and its standard error from the passes;
* many independent references shaped like the test's (16 passes x 64 spp): the
  distribution of their block statistic against the high-spp value, to see whether the
  test's reference estimator is calibrated (mean 0, sd 1) or skewed.

Writes ``benchmarks/results/sparse_single_block.{md,json}``.

    python3 -m benchmarks.sparse_single_block        # about 5 minutes on 2 cores
"""
from __future__ import annotations

import argparse
import datetime
import json
import tempfile
import time
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import mitsuba as mi
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
from benchmarks.harness import cpu_model

OURS = {"type": "volpath_raymarch", "step_size": 0.04, "mode": "single", "max_depth": 2,
        "step_mode": "majorant", "step_optical_depth": 0.05}
#: the block: offset (x, y) and size in the 32x32 image
OFFSET, SIZE, CHANNEL = (8, 8), 8, 2
#: the test's reference: block mean and its standard error (from the pixels' standard
#: errors, as stats.block_estimate), measured by running the test's comparison
TEST_REFERENCE = (0.149017, 3.59e-5)


def cropped_scene() -> mi.Scene:
    """scenes/sparse.xml at 32x32 with its film cropped to the block."""
    crop = (f'<integer name="crop_offset_x" value="{OFFSET[0]}"/>'
            f'<integer name="crop_offset_y" value="{OFFSET[1]}"/>'
            f'<integer name="crop_width" value="{SIZE}"/><integer name="crop_height" value="{SIZE}"/>')
    xml = (ROOT / "scenes" / "sparse.xml").read_text().replace(
        '<string name="pixel_format" value="rgb"/>', '<string name="pixel_format" value="rgb"/>' + crop)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sparse_crop.xml"
        path.write_text(xml)
        mi.file_resolver().prepend(str(ROOT / "scenes"))
        return mi.load_file(str(path), res="32", max_depth="2")


def passes(scene, integrator: dict, n: int, spp: int, seed: int) -> np.ndarray:
    it = mi.load_dict(integrator)
    return np.stack([np.array(mi.render(scene, integrator=it, spp=spp, seed=seed + k), np.float64)
                     for k in range(n)])


def block_mean(images: np.ndarray) -> np.ndarray:
    """Per-pass block mean of the channel."""
    return images[..., CHANNEL].mean(axis=(1, 2))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--passes", type=int, default=64, help="passes of each high-spp estimate")
    ap.add_argument("--groups", type=int, default=64, help="test-shaped references drawn")
    args = ap.parse_args()
    mi.set_variant("llvm_ad_rgb")
    scene = cropped_scene()
    rows, t0 = {}, time.perf_counter()
    for name, integrator, spp, seed in (("volpath_raymarch single", OURS, 256, 1000),
                                        ("volpath", {"type": "volpath", "max_depth": 2}, 4096, 0),
                                        ("volpath_delta", {"type": "volpath_delta", "max_depth": 2},
                                         1024, 70000)):
        b = block_mean(passes(scene, integrator, args.passes, spp, seed))
        rows[name] = {"spp_per_pixel": args.passes * spp, "mean": float(b.mean()),
                      "se": float(b.std(ddof=1) / np.sqrt(len(b)))}
        print(name, rows[name], flush=True)
    truth = rows["volpath"]["mean"]
    # test-shaped references: 16 passes x 64 spp, block se from the pixels' se
    P = passes(scene, {"type": "volpath", "max_depth": 2}, 16 * args.groups, 64, 100000)
    z = []
    for g in range(args.groups):
        x = P[16 * g:16 * (g + 1), ..., CHANNEL]
        se = np.sqrt((x.std(axis=0, ddof=1) ** 2 / 16).sum()) / SIZE ** 2
        z.append((x.mean() - truth) / se)
    z = np.array(z)
    groups = {"count": args.groups, "z_mean": float(z.mean()), "z_sd": float(z.std(ddof=1)),
              "z_min": float(z.min()), "z_max": float(z.max()),
              "fraction_abs_z_over_3": float(np.mean(np.abs(z) > 3))}
    test_z = (TEST_REFERENCE[0] - truth) / TEST_REFERENCE[1]
    result = {"date": datetime.date.today().isoformat(), "cpu": cpu_model(),
              "block": {"offset": OFFSET, "size": SIZE, "channel": CHANNEL},
              "estimates": rows, "test_reference": {"mean": TEST_REFERENCE[0],
                                                    "se": TEST_REFERENCE[1], "z": test_z},
              "test_shaped_references": groups,
              "seconds": time.perf_counter() - t0}
    out = ROOT / "benchmarks" / "results"
    (out / "sparse_single_block.json").write_text(json.dumps(result, indent=1))
    lines = ["# The sparse single-scattering block (tests/integrators/test_volpath_raymarch.py)", "",
             f"`python3 -m benchmarks.sparse_single_block` on {result['date']} ({result['cpu']}), "
             f"{result['seconds']:.0f} s. Block rows/columns 8-15 of scenes/sparse.xml at 32x32, "
             "blue, max_depth 2.", "",
             "| estimate | spp per pixel | block mean | se (from passes) |", "|---|---|---|---|"]
    lines += [f"| {k} | {v['spp_per_pixel']} | {v['mean']:.6f} | {v['se']:.6f} |"
              for k, v in rows.items()]
    lines += [f"| the test's reference (volpath, seeds 0-15, 16 x 64 spp) | 1024 | "
              f"{TEST_REFERENCE[0]:.6f} | {TEST_REFERENCE[1]:.6f} |", "",
              f"The test's reference lies z = {test_z:+.2f} from the volpath estimate at "
              f"{rows['volpath']['spp_per_pixel']} spp. {args.groups} independent references "
              f"shaped like it (16 x 64 spp, seeds 100000+): z mean {groups['z_mean']:+.2f}, "
              f"sd {groups['z_sd']:.2f}, range [{groups['z_min']:.2f}, {groups['z_max']:.2f}], "
              f"|z| > 3 in {groups['fraction_abs_z_over_3']:.1%}."]
    (out / "sparse_single_block.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
