"""Thin glue between the tests and the shared harness in mitsuba_plugins.stats."""
from __future__ import annotations

import os
from pathlib import Path

import mitsuba as mi
import numpy as np

from mitsuba_plugins import stats

SCENES = Path(__file__).resolve().parents[1] / "scenes"
FAILURES = Path(os.environ.get("MITSUBA_PLUGINS_TEST_OUT", Path(__file__).resolve().parents[1] / "out" / "test-failures"))


def load(scene: str, **params) -> mi.Scene:
    return mi.load_file(str(SCENES / f"{scene}.xml"), **{k: str(v) for k, v in params.items()})


def estimate(scene, integrator: dict, passes: int, spp: int, seed: int) -> stats.Estimate:
    est = stats.render_passes(scene, passes, spp, integrator=mi.load_dict(integrator),
                              seed=seed, warmup=False)
    assert est.invalid == 0, f"{integrator}: {est.invalid} NaN/Inf pixel values"
    return est


def assert_same_expectation(a: stats.Estimate, b: stats.Estimate, name: str, **kw):
    """VALIDATION.md's three checks; on failure the images and the z map are written."""
    result = stats.compare(a, b, **kw)
    if not result.passed:
        FAILURES.mkdir(parents=True, exist_ok=True)
        for tag, img in (("candidate", a.mean), ("reference", b.mean), ("z", result.z)):
            mi.Bitmap(np.ascontiguousarray(img, dtype=np.float32)).write(str(FAILURES / f"{name}_{tag}.exr"))
    assert result.passed, f"{name}: {result.summary()} (images in {FAILURES})"
    return result


def assert_mean_equals(images, expected: float, name: str, alpha: float = 1e-3):
    """t-test of independent pixel values (one channel: gray scenes) against ``expected``."""
    res = stats.t_test(np.asarray(images)[..., 0], expected)
    assert res.p > alpha, f"{name}: {res.summary()}"
    return res
