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

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANT
from helpers import assert_same_expectation, camera, estimate, homogeneous, load, media_scene
from mitsuba_plugins.tracking import scene_media

BACKEND = VARIANT.split("_", 1)[0]
SPECTRAL = f"{BACKEND}_ad_spectral"
MONO = f"{BACKEND}_ad_mono"
RGB = f"{BACKEND}_ad_rgb"
VARIANTS = (SPECTRAL, MONO)
RES = 16
DEPTH = 8


@pytest.fixture(scope="module", params=VARIANTS, ids=lambda v: v.split("_")[-1])
def other_variant(request):
    """The spectral / mono variant a test runs in (conftest's ``variant`` switches)."""
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


def _against(scene, name, reference="volpath", depth=DEPTH, **params):
    settings = {} if depth is None else {"max_depth": depth}
    a = estimate(scene, {"type": name, **settings, **params}, passes=8, spp=32, seed=1000)
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


def test_decomposition_tracking_in_a_mitsuba_medium(other_variant):
    """Decomposition tracking's control collisions weigh by the albedo of Mitsuba's
    ``heterogeneous`` medium; in spectral variants that albedo was a plain Array4f, which
    the walk's loop refused as the throughput's type (found in issue 29)."""
    _against(load("smoke_heterogeneous", res=RES), "volpath_delta",
             free_flight="decomposition")


@pytest.mark.parametrize("integrator,builtin,depth", [("path_rr", "path", DEPTH),
                                                     ("direct_mis", "direct", None)])
def test_surfaces_against_builtin(other_variant, integrator, builtin, depth):
    _against(load("cornell_box", res=RES), integrator, reference=builtin, depth=depth)


@pytest.mark.parametrize("integrator,builtin,depth", [("path_rr", "path", 3),
                                                     ("direct_mis", "direct", None)])
def test_power_emitter_selection_against_builtin(other_variant, integrator, builtin, depth):
    """``emitter_selection = power`` reduces each emitter's sampled flux to one number:
    luminance in RGB, the mean over the sampled wavelengths elsewhere (that branch called
    ``dr.depth``, which Dr.Jit 1 does not have, and crashed every non-RGB render)."""
    _against(load("veach_mis", res=RES), integrator, reference=builtin, depth=depth,
             emitter_selection="power")


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
    from mitsuba_plugins.tracking.trackers import index_channel
    spec = mi.Spectrum(1.0, 2.0, 3.0, 4.0)
    got = [index_channel(spec, mi.UInt32(c))[0] for c in range(4)]
    assert np.allclose(got, [1, 2, 3, 4])


def test_polarized_variant_is_refused_with_one_line():
    from mitsuba_plugins.registry import UnsupportedVariantError, check_variant
    with pytest.raises(UnsupportedVariantError, match="polarized rendering is not implemented"):
        check_variant(f"{BACKEND}_ad_spectral_polarized")


# -- grid_medium in spectral and mono variants ------------------------------------------
@pytest.fixture(scope="module")
def rgb_grids(tmp_path_factory):
    """A gray and an RGB grid (with empty space and a black corner) as .vol files."""
    from mitsuba_plugins.grids import gridio
    root = tmp_path_factory.mktemp("variant_grids")
    rng = np.random.default_rng(11)
    gray = (rng.random((10, 12, 9)) ** 2 * 2.0).astype(np.float32)
    gray[:3, :4, :3] = 0.0
    rgb = gray[..., None] * rng.uniform(0.05, 1.0, (10, 12, 9, 3)).astype(np.float32)
    gridio.write_vol(root / "gray.vol", gray)
    gridio.write_vol(root / "rgb.vol", rgb)
    return root


def _grid_pair(path, storage="dense", interpolation="trilinear", **kw):
    tw = mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)
    ours = {"type": "grid_medium", "filename": str(path), "scale": 3.0, "to_world": tw,
            "storage": storage, "interpolation": interpolation, **kw}
    theirs = {"type": "heterogeneous", "scale": 3.0,
              "sigma_t": {"type": "gridvolume", "filename": str(path), "to_world": tw,
                          "filter_type": interpolation}, **kw}
    return ours, theirs


@pytest.mark.parametrize("storage", ["dense", "sparse"])
@pytest.mark.parametrize("interpolation", ["trilinear", "nearest"])
@pytest.mark.parametrize("name", ["gray.vol", "rgb.vol"])
def test_grid_medium_lookups_equal_gridvolume(other_variant, rgb_grids, name, storage,
                                              interpolation):
    """grid_medium's extinction equals heterogeneous + gridvolume's (up to float rounding)
    at random points and wavelengths (RGB upsampled as gridvolume does in spectral variants, its luminance in
    mono), and its global majorant bounds every value."""
    ours, theirs = _grid_pair(rgb_grids / name, storage, interpolation)
    ours, theirs = mi.load_dict(ours), mi.load_dict(theirs)
    rng = np.random.default_rng(2)
    n = 8192
    p = rng.uniform(-0.99, 0.99, (n, 3)).astype(np.float32)
    mei = dr.zeros(mi.MediumInteraction3f, n)
    mei.p = mi.Point3f(*(mi.Float(p[:, i]) for i in range(3)))
    if mi.is_spectral:
        mei.wavelengths = mi.Spectrum(*[mi.Float(rng.uniform(
            mi.MI_CIE_MIN, mi.MI_CIE_MAX, n).astype(np.float32)) for _ in range(4)])
    a = np.array(ours.eval_sigma_t(mei))
    _, _, b = theirs.get_scattering_coefficients(mei)
    b = np.array(b)
    assert np.all(np.isfinite(a))
    # float rounding of the interpolation weights (CUDA's hardware textures interpolate
    # with 8-bit weights, on both sides, tests/grids/test_sparse_storage.py)
    tol = 3 * 2.0 ** -9 if mi.variant().startswith("cuda") else 4e-6
    assert np.max(np.abs(a - b)) <= tol * b.max(), np.max(np.abs(a - b)) / b.max()
    assert a.max() <= float(ours.global_majorant[0])


@pytest.mark.parametrize("storage", ["dense", "sparse"])
def test_grid_medium_majorant_cells_bound_extinction(other_variant, rgb_grids, storage):
    """Every majorant segment bounds the extinction along random rays, at random
    wavelengths: an RGB grid (spectral: the product of the spectrum's and the scale's
    cell maxima) and a gray grid times a chromatic multiplier."""
    from helpers import check_segment_bounds
    for name, factor in (("rgb.vol", 1.0), ("gray.vol", [1.0, 0.3, 0.05])):
        medium = mi.load_dict(dict(_grid_pair(rgb_grids / name, storage)[0], sigma_t=factor,
                                   majorant_resolution=4))
        assert medium.majorant_grid.resolution == (4, 4, 4)
        check_segment_bounds(medium, medium.majorant_grid)


@pytest.mark.parametrize("integrator", ["volpath_delta", "volpath_raymarch"])
@pytest.mark.parametrize("storage", ["dense", "sparse"])
def test_rgb_grid_medium_against_heterogeneous(other_variant, rgb_grids, storage, integrator):
    """An RGB grid through grid_medium renders what heterogeneous + gridvolume of the same
    file renders through volpath."""
    ours, theirs = _grid_pair(rgb_grids / "rgb.vol", storage, albedo=0.8)
    sensor = camera(res=RES, origin=(0.0, 1.2, 4.0))
    a = estimate(media_scene(ours, sensor=sensor), {"type": integrator, "max_depth": DEPTH},
                 passes=8, spp=32, seed=1000)
    b = estimate(media_scene(theirs, sensor=sensor), {"type": "volpath", "max_depth": DEPTH},
                 passes=8, spp=64, seed=0)
    assert_same_expectation(a, b, f"{mi.variant()}-{integrator}-rgb_grid-{storage}")


def _nested(kind: str, rgb_grids) -> dict:
    """A nested chromatic sigma_t volume: an RGB gridvolume or an rgb constvolume."""
    if kind == "gridvolume":
        return {"type": "gridvolume", "filename": str(rgb_grids / "rgb.vol"),
                "to_world": mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)}
    return {"type": "constvolume", "value": {"type": "rgb", "value": [1.0, 0.2, 1.0]}}


@pytest.mark.parametrize("integrator", ["volpath", "volpath_delta", "volpath_raymarch"])
@pytest.mark.parametrize("kind", ["gridvolume", "constvolume"])
def test_nested_chromatic_volume_against_heterogeneous(other_variant, rgb_grids, kind,
                                                       integrator):
    """grid_medium with a nested chromatic sigma_t volume renders what heterogeneous
    with it renders. Both once went wrong: a constvolume reports 0 channels and an RGB
    gridvolume 0 in spectral variants, so the medium called itself gray (volpath's
    green of (1, 0.2, 1) 24 sigma off), and in spectral variants the RGB grid was
    refused (its model coefficients checked >= 0)."""
    from mitsuba_plugins.grids.nested_volume import volume_channels
    sigma_t = _nested(kind, rgb_grids)
    chromatic = not (mi.is_monochromatic and kind == "constvolume")
    assert volume_channels(mi.load_dict(sigma_t)) == (3 if chromatic else 1)
    common = {"scale": 2.0, "albedo": 0.8, "sigma_t": sigma_t}
    sensor = camera(res=RES)
    a = estimate(media_scene(dict(common, type="grid_medium"), sensor=sensor),
                 {"type": integrator, "max_depth": DEPTH}, passes=8, spp=32, seed=1000)
    b = estimate(media_scene(dict(common, type="heterogeneous"), sensor=sensor),
                 {"type": "volpath", "max_depth": DEPTH}, passes=8, spp=64, seed=0)
    assert_same_expectation(a, b, f"{mi.variant()}-{integrator}-nested-{kind}")


@pytest.mark.parametrize("name", ["smoke", "chromatic", "sparse"])
def test_suite_media_scenes_against_volpath(other_variant, name):
    """The suite's own grid_medium scenes: volpath_delta against Mitsuba's volpath with
    the same medium (through Mitsuba's interface: one global majorant)."""
    _against(load(name, res=RES), "volpath_delta")


@pytest.mark.parametrize("integrator", [{"type": "volpath_delta"},
                                        {"type": "volpath_raymarch"},
                                        {"type": "volpath_raymarch", "mode": "single"}],
                         ids=["delta", "raymarch", "raymarch_single"])
def test_emission_matches_an_area_light_of_the_same_radiance(other_variant, integrator):
    """An emissive absorbing slab (gray extinction 1 over d = 2, Le = (2, 1, 0.5)) sends
    (1 - exp(-2)) of what a rectangle emitter of radiance Le sends (section 6's
    convention): in spectral variants RGB emission is upsampled as an emitter's radiance
    is (an RGB white stays white), in mono it is its luminance. z-test of the image means
    (pixels independent; 8x8 orthographic view). The single-scattering march once
    crashed here in spectral variants (its cell integral was a plain Array4f)."""
    from helpers import emissive_slab
    from mitsuba_plugins.tools import stats
    Le = [2.0, 1.0, 0.5]
    slab = emissive_slab(Le, sigma_t={"type": "constvolume", "value": 1.0,
                                      "to_world": mi.ScalarTransform4f().translate(
                                          [-1, -1, -1]).scale(2)})
    T = mi.ScalarTransform4f
    card = mi.load_dict({
        "type": "scene",
        "card": {"type": "rectangle", "to_world": T().scale(2),
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": Le}}},
        "sensor": {"type": "orthographic",
                   "to_world": T().look_at([0, 0, 5], [0, 0, 0], [0, 1, 0]) @ T().scale(
                       [0.5, 0.5, 1]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8,
                            "rfilter": {"type": "box"}}}})
    f = 1.0 - np.exp(-2.0)
    a = np.array(mi.render(slab, integrator=mi.load_dict(integrator), spp=512,
                           seed=3)).reshape(64, -1)
    b = np.array(mi.render(card, integrator=mi.load_dict({"type": "path"}), spp=512,
                           seed=4)).reshape(64, -1)
    for c in range(a.shape[1]):
        se = np.sqrt(a[:, c].var(ddof=1) / 64 + f ** 2 * b[:, c].var(ddof=1) / 64)
        # a floor of 2e-4 relative: the single-scattering march and the uniform card are
        # deterministic in mono (zero variance); float32 sums differ by ~7e-5 there
        z = (a[:, c].mean() - f * b[:, c].mean()) / max(se, 2e-4 * f * b[:, c].mean(), 1e-7)
        assert abs(z) < stats.sidak_z(1e-3, a.shape[1]), \
            f"channel {c}: {a[:, c].mean():.5f} vs {f:.4f} x {b[:, c].mean():.5f} (z {z:.2f})"


def test_a_mitsuba_majorant_below_the_extinction_is_replaced():
    """Mitsuba's heterogeneous with a constant rgb sigma_t reports scale x max() of the
    upsampled spectrum, 0.84 for (1, 0.2, 1), below the spectrum's 0.9998 in spectral
    variants: tracking with it would be biased. Our trackers check it at sampled points
    and wavelengths and use the largest extinction seen instead; in RGB it stays."""
    from mitsuba_plugins.tracking.trackers import probe_interaction, tracker_for
    def medium():
        return mi.load_dict({"type": "heterogeneous", "scale": 3.0, "sigma_t": {
            "type": "constvolume", "value": {"type": "rgb", "value": [1.0, 0.2, 1.0]}}})
    mi.set_variant(SPECTRAL)
    m = medium()
    reported = float(np.max(np.array(m.get_majorant(probe_interaction(1)))))
    _, _, sigma_t = m.get_scattering_coefficients(probe_interaction(1024))
    assert reported < 0.9 * float(np.max(np.array(sigma_t)))       # Mitsuba's is too small
    bound = float(tracker_for(m).grid.outside[0])
    assert bound >= float(np.max(np.array(sigma_t)))
    mi.set_variant(RGB)
    m = medium()
    assert float(tracker_for(m).grid.outside[0]) == \
        float(np.max(np.array(m.get_majorant(probe_interaction(1)))))
