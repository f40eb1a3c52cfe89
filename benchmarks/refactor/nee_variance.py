"""Which term of ``volpath_delta``'s estimate carries the variance: light found by
emitter sampling (``nee``) or by phase/BSDF sampling (``emission``), rendered alone
through ``instrument.only_terms``. Per scene, the relative variance of one 16-spp render
(per-pixel variance over 24 seeds, weighted by 1 / (mean^2 + 0.01) as the relMSE is),
then each term's own relative variance as a fraction of the whole estimate's. Issue 29
asked it of the tuning half's homogeneous spheres before trying to split next-event
estimation: splitting only reduces the variance of the light sample at a given vertex.

    python3 benchmarks/refactor/nee_variance.py [case ...]   (default: the tuning spheres)
"""
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
import mitsuba_plugins  # noqa: E402,F401  -- chooses libLLVM before drjit loads
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant("llvm_ad_rgb")
import dense_heldout  # noqa: E402
from mitsuba_plugins import instrument  # noqa: E402

SEEDS, SPP, RES = 24, 16, 32
DEFAULT = ("tuning04_sphere_spot", "tuning12_sphere_area", "tuning20_sphere_env")


def term_variance(scene, terms):
    """(mean, per-pixel variance) over SEEDS renders of only ``terms``."""
    with instrument.only_terms(*terms):
        images = np.stack([np.array(mi.render(scene, integrator=mi.load_dict(
            {"type": "volpath_delta"}), spp=SPP, seed=s)) for s in range(SEEDS)])
    return images.mean(axis=0), images.var(axis=0, ddof=1)


def main(names) -> None:
    cases = {c.name: c for c in dense_heldout.family()}
    tmp = Path(tempfile.mkdtemp())
    for name in names:
        scene = dense_heldout.scene(cases[name], RES, tmp)
        mean, var = term_variance(scene, instrument.TERMS)
        weight = 1.0 / (mean ** 2 + 1e-2)
        total = float((var * weight).mean())
        parts = {t: float((term_variance(scene, (t,))[1] * weight).mean()) / total
                 for t in instrument.TERMS}
        print(f"{name}: relative variance {total:.4g}; as fractions of it: "
              + ", ".join(f"{t} alone {f:.2f}" for t, f in parts.items()))


if __name__ == "__main__":
    main(sys.argv[1:] or DEFAULT)
