"""Spectral and monochrome variants (issue 24): every plugin renders what Mitsuba's own
integrators render in the same variant (docs/validation.md's three checks: per-pixel
Welch test with Sidak correction, 8x8 blocks, image mean; disjoint seeds).

The variants are the test variant's backend with ``_ad_spectral`` and ``_ad_mono``
(``llvm_ad_spectral`` / ``llvm_ad_mono`` on CPU, ``cuda_`` twins on a GPU). In a spectral
variant a path carries 4 sampled wavelengths: a medium whose RGB extinction Mitsuba
upsamples to a spectrum is chromatic there, and the hero channel of spectral MIS is one
of 4 wavelengths. Both once went wrong silently (a chromatic cube rendered ~2x too
bright): the chromaticity probe read the extinction at wavelength 0 for every channel,
and the hero lookup knew 3 channels only.
"""
from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANT
from helpers import assert_same_expectation, camera, estimate, homogeneous, load, media_scene
from mitsuba_plugins import scene_media

BACKEND = VARIANT.split("_", 1)[0]
SPECTRAL = f"{BACKEND}_ad_spectral"
MONO = f"{BACKEND}_ad_mono"
VARIANTS = (SPECTRAL, MONO)
RES = 16
DEPTH = 8


@pytest.fixture(params=VARIANTS, ids=lambda v: v.split("_")[-1])
def other_variant(request):
    """Switch to a spectral / mono variant (the conftest fixture switches back)."""
    mi.set_variant(request.param)
    return request.param


def chromatic_cube() -> mi.Scene:
    """Issue 24's reproduction: a homogeneous cube of RGB extinction 0.2/0.5/0.9 x 2,
    albedo 0.8, over a diffuse floor under a constant emitter (it rendered 1.22 through
    volpath_delta in llvm_ad_spectral against volpath's 0.63)."""
    T = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene",
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "floor": {"type": "rectangle",
                  "to_world": T().translate([0, -1.0, 0]).rotate([1, 0, 0], -90).scale(4),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}},
        "cube": {"type": "cube", "bsdf": {"type": "null"}, "to_world": T().scale(0.8),
                 "interior": {"type": "homogeneous", "scale": 2.0, "albedo": 0.8,
                              "sigma_t": {"type": "rgb", "value": [0.2, 0.5, 0.9]}}},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at([0, 1.5, 4.5], [0, -0.2, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": RES, "height": RES,
                            "rfilter": {"type": "box"}}}})


def _against(scene, name, reference="volpath", depth=DEPTH):
    settings = {} if depth is None else {"max_depth": depth}
    a = estimate(scene, {"type": name, **settings}, passes=8, spp=32, seed=1000)
    b = estimate(scene, {"type": reference, **settings}, passes=8, spp=64, seed=0)
    return assert_same_expectation(a, b, f"{mi.variant()}-{name}")


SCENES = {
    "chromatic_cube": chromatic_cube,
    "hg_chromatic_ball": lambda: media_scene(homogeneous([0.5, 1.0, 2.0], albedo=0.9, g=0.6),
                                             sensor=camera(res=RES)),
    "smoke_heterogeneous": lambda: load("smoke_heterogeneous", res=RES),
}


@pytest.mark.parametrize("integrator", ["volpath_delta", "volpath_raymarch"])
@pytest.mark.parametrize("case", list(SCENES))
def test_media_against_volpath(other_variant, case, integrator):
    _against(SCENES[case](), integrator)


@pytest.mark.parametrize("integrator,builtin,depth", [("path_rr", "path", DEPTH),
                                                     ("direct_mis", "direct", None)])
def test_surfaces_against_builtin(other_variant, integrator, builtin, depth):
    _against(load("cornell_box", res=RES), integrator, reference=builtin, depth=depth)


def test_spectral_rgb_extinction_is_chromatic():
    """In a spectral variant an RGB extinction varies with wavelength (chromatic: spectral
    MIS), a gray one does not (no spectral machinery); in mono nothing is chromatic."""
    mi.set_variant(SPECTRAL)
    tinted = mi.load_dict(homogeneous([0.2, 0.5, 0.9]))
    gray = mi.load_dict(homogeneous(0.7))
    assert scene_media._is_chromatic(tinted) and not scene_media._is_chromatic(gray)
    mi.set_variant(MONO)
    assert not scene_media.SceneMedia(chromatic_cube()).chromatic


def test_index_channel_reads_every_wavelength():
    mi.set_variant(SPECTRAL)
    from mitsuba_plugins.contract import index_channel
    spec = mi.Spectrum(1.0, 2.0, 3.0, 4.0)
    got = [index_channel(spec, mi.UInt32(c))[0] for c in range(4)]
    assert np.allclose(got, [1, 2, 3, 4])


def test_polarized_variant_is_refused_with_one_line():
    from mitsuba_plugins.registry import UnsupportedVariantError, check_variant
    with pytest.raises(UnsupportedVariantError, match="polarized rendering is not implemented"):
        check_variant(f"{BACKEND}_ad_spectral_polarized")
