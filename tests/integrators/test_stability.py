"""Hard cases, every integrator x every case where it applies (issue 6).

Every render asserts zero NaN/Inf samples (counted in the kernel, see helpers.render and
helpers.estimate). Then, per case:

* surfaces (tiny lights on roughness-0.001 plates, delta lights only, grazing camera
  rays): our integrators draw Mitsuba's random numbers in Mitsuba's order, so each image
  must equal the built-in's at the same seed up to float rounding (``direct_mis`` vs
  ``direct``; ``path_rr``, and ``volpath_*`` on a scene without media, vs ``path``);
* media: the docs/validation.md z-tests against ``volpath`` (8 passes x 32 spp against
  16 x 64 spp at 24x24, Sidak-corrected; 16 spp per pass at 8x8 for the dense grids), or, where ``volpath`` is wrong (chromatic extinction),
  against channel-wise gray ``volpath`` references, with the built-in's failure measured;
* furnaces: albedo-1 media in a uniform environment of radiance 1 render 1 (t-test);
  single scattering may only lose energy (one-sided bound).

``volpath_raymarch`` is biased by design. It is held to the reference where marching is
exact or its bias is far below the noise: homogeneous media (never marched), the empty
grid, the 1e-4 and 1e4 grids. For the one dense voxel (1e4 in one voxel of an 8^3 grid)
a 0.02 step resolves the voxel's trilinear tent coarsely; there it must render finite
and respect the furnace.
"""
import re

import mitsuba as mi
import numpy as np
import pytest

from helpers import (HARD_MEDIA, LUMINANCE, SCENES, SPARSE, assert_same_expectation,
                     assert_same_render, camera, estimate, grid, homogeneous, media_scene,
                     render)
from mitsuba_plugins.tools import stats

RES = 24
DEPTH = 8
#: volpath crosses a 1e4 grid in ~2e4 null collisions (one global majorant): 2.3 ms per
#: path measured, so the dense grids are rendered at 8x8, and compared with 16 spp per
#: pass where volpath is the reference
DENSE_RES, DENSE = 8, ("one_dense_voxel",)
#: Where volpath is not the reference. On the 1e4 smoke grid volpath's image mean is 1.0%
#: below ours: 0.2520 against 0.2545 (volpath_delta, track_length and ratio shadows) at
#: 8x8, image-mean z = -3.2 on two independent seed sets (16 x 16 and 16 x 32 spp). A
#: ray march, whose distances involve no tracking at all, converges to ours as its step
#: shrinks (0.2549, 0.2546, 0.2545, 0.2545 at steps 0.02, 0.01, 0.005, 0.0025; se 4e-4),
#: so that fine march is the reference here and volpath's figure is reported.
REFERENCES = {"grid_extinction_1e4": {"type": "volpath_raymarch", "step_size": 0.0025}}
T = mi.ScalarTransform4f


# -- surfaces ---------------------------------------------------------------------------------
def _plates_and_tiny_lights():
    """Veach's MIS scene (scenes/veach_mis.xml) with every plate at roughness 0.001 and
    every light 10x smaller (radius 0.003 to 0.09, radiance 100x: the same power)."""
    xml = (SCENES / "veach_mis.xml").read_text()
    xml = re.sub(r'name="alpha" value="[0-9.]+"', 'name="alpha" value="0.001"', xml)
    xml = re.sub(r'name="radius" value="([0-9.]+)"',
                 lambda m: f'name="radius" value="{float(m.group(1)) / 10:g}"', xml)
    xml = re.sub(r'<emitter type="area"><rgb name="radiance" value="([0-9.]+)"/>',
                 lambda m: f'<emitter type="area"><rgb name="radiance" value="{float(m.group(1)) * 100:g}"/>',
                 xml)
    return mi.load_string(xml, res=str(RES))


def _delta_light_scene(kind):
    """A diffuse floor and box and a roughness-0.001 plate, lit by one delta light only."""
    light = {"point": {"type": "point", "position": [0.5, 1.8, 1.0],
                       "intensity": {"type": "rgb", "value": 8.0}},
             "spot": {"type": "spot", "to_world": T().look_at([0.5, 2.0, 1.0], [0, -1, 0], [0, 0, 1]),
                      "cutoff_angle": 35.0, "intensity": {"type": "rgb", "value": 12.0}},
             "directional": {"type": "directional", "direction": [-0.4, -1.0, -0.3],
                             "irradiance": {"type": "rgb", "value": 2.0}}}[kind]
    return mi.load_dict({
        "type": "scene", "light": light,
        "floor": {"type": "rectangle", "to_world": T().translate([0, -1, 0]).rotate(
            [1, 0, 0], -90).scale(4), "bsdf": {"type": "diffuse"}},
        "box": {"type": "cube", "to_world": T().translate([-0.6, -0.6, -0.3]).scale(0.4),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.3, 0.2]}}},
        "plate": {"type": "rectangle", "to_world": T().translate([0.7, -0.5, -0.5]).rotate(
            [1, 0, 0], -50).scale(0.6),
                  "bsdf": {"type": "roughconductor", "alpha": 0.001}},
        "sensor": camera(res=RES)})


def _grazing_camera():
    """The camera 1e-3 above an infinite-looking plane, looking along it (rays meet the
    plane at up to 89.98 degrees from its normal), lit by a grazing sun and the sky."""
    return mi.load_dict({
        "type": "scene",
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 0.3}},
        "sun": {"type": "directional", "direction": [0.0, -0.05, -1.0],
                "irradiance": {"type": "rgb", "value": 3.0}},
        "plane": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(1000),
                  "bsdf": {"type": "roughconductor", "alpha": 0.001}},
        "bump": {"type": "sphere", "center": [0, 0.2, -8], "radius": 0.2,
                 "bsdf": {"type": "diffuse"}},
        "sensor": camera(res=RES, origin=(0, 1e-3, 0), target=(0, 1e-3, -1), fov=20)})


SURFACE_CASES = {
    "tiny_lights_on_plates": _plates_and_tiny_lights,
    "point_light_only": lambda: _delta_light_scene("point"),
    "spot_light_only": lambda: _delta_light_scene("spot"),
    "directional_light_only": lambda: _delta_light_scene("directional"),
    "grazing_camera_rays": _grazing_camera,
}
#: each of ours on a scene without media, and the built-in that draws the same numbers
SURFACE_TWINS = {"direct_mis": "direct", "path_rr": "path", "volpath_delta": "path",
                 "volpath_raymarch": "path"}


@pytest.mark.parametrize("case", list(SURFACE_CASES))
@pytest.mark.parametrize("ours", list(SURFACE_TWINS))
def test_surface_case_equals_builtin(ours, case):
    scene = SURFACE_CASES[case]()
    depth = {} if ours == "direct_mis" else {"max_depth": DEPTH}
    a = render(scene, {"type": ours, **depth}, spp=16, seed=5)
    b = render(scene, {"type": SURFACE_TWINS[ours], **depth}, spp=16, seed=5)
    assert (a >= 0).all() and a.max() > 0, case
    assert_same_render(a, b)


# -- media ------------------------------------------------------------------------------------
def _delta_lit_media(kind):
    """The medium ball over the floor, lit by one delta light only (no environment)."""
    light = {"point": {"type": "point", "position": [1.2, 1.8, 1.0],
                       "intensity": {"type": "rgb", "value": 10.0}},
             "spot": {"type": "spot", "to_world": T().look_at([0.0, 2.5, 0.3], [0, 0, 0], [0, 0, 1]),
                      "cutoff_angle": 30.0, "intensity": {"type": "rgb", "value": 15.0}},
             "directional": {"type": "directional", "direction": [-0.5, -1.0, -0.4],
                             "irradiance": {"type": "rgb", "value": 2.0}}}[kind]
    scene = {"type": "scene", "light": light,
             "floor": {"type": "rectangle", "to_world": T().translate([0, -1.05, 0]).rotate(
                 [1, 0, 0], -90).scale(4), "bsdf": {"type": "diffuse"}},
             "ball": {"type": "sphere", "bsdf": {"type": "null"},
                      "interior": homogeneous(1.2, albedo=0.9, g=0.4)},
             "sensor": camera(res=RES)}
    return mi.load_dict(scene)


def _emitter_inside_medium():
    """A small area light inside the fog ball (its exterior is the fog)."""
    fog = {"type": "ref", "id": "fog"}
    return media_scene(fog, sensor=camera(res=RES), env=0.0, extra={
        "fog": homogeneous(0.8, albedo=0.8, g=0.2),
        "inner_light": {"type": "sphere", "center": [0.2, -0.1, 0.1], "radius": 0.12,
                        "exterior": fog, "emitter": {"type": "area", "radiance": {
                            "type": "rgb", "value": 30.0}}}})


def _camera_inside_medium():
    fog = {"type": "ref", "id": "fog"}
    return media_scene(homogeneous(2.0, albedo=0.9), sensor=camera(res=RES, medium=fog), extra={
        "fog": homogeneous(0.25, albedo=0.9, g=0.5),
        "room": {"type": "sphere", "radius": 8.0, "bsdf": {"type": "null"}, "interior": fog}})


def _grazing_medium():
    """Camera rays skim the top face of a medium slab (within 0.3 degrees of it)."""
    return media_scene(sensor=camera(res=RES, origin=(0, 0.503, 4.0), target=(0, 0.49, 0), fov=12),
                       extra={"slab": {"type": "cube", "bsdf": {"type": "null"},
                                       "to_world": T().scale([1.5, 0.5, 1.5]),
                                       "interior": homogeneous(3.0, albedo=0.9)}})


#: medium hard cases: (scene builder of a tmp folder, does volpath_raymarch match volpath)
MEDIA_CASES = {
    "extinction_1e-4": (lambda tmp: media_scene(homogeneous(1e-4), sensor=camera(res=RES)), True),
    "extinction_1e4": (lambda tmp: media_scene(homogeneous(1e4), sensor=camera(res=RES)), True),
    "grid_extinction_1e-4": (lambda tmp: media_scene(HARD_MEDIA["grid_1e-4"](tmp),
                                                     sensor=camera(res=RES)), True),
    "grid_extinction_1e4": (lambda tmp: media_scene(HARD_MEDIA["grid_1e4"](tmp),
                                                    sensor=camera(res=DENSE_RES)), True),
    "hg_g_-0.99": (lambda tmp: media_scene(homogeneous(2.0, albedo=0.95, g=-0.99),
                                           sensor=camera(res=RES)), True),
    "hg_g_0": (lambda tmp: media_scene(homogeneous(2.0, albedo=0.95, g=0.0),
                                       sensor=camera(res=RES)), True),
    "hg_g_0.99": (lambda tmp: media_scene(homogeneous(2.0, albedo=0.95, g=0.99),
                                          sensor=camera(res=RES)), True),
    "empty_grid": (lambda tmp: media_scene(HARD_MEDIA["empty_grid"](tmp), sensor=camera(res=RES)),
                   True),
    "one_dense_voxel": (lambda tmp: media_scene(HARD_MEDIA["one_dense_voxel"](tmp),
                                                sensor=camera(res=DENSE_RES)), False),
    "camera_inside_medium": (lambda tmp: _camera_inside_medium(), True),
    "emitter_inside_medium": (lambda tmp: _emitter_inside_medium(), True),
    "point_light_only": (lambda tmp: _delta_lit_media("point"), True),
    "spot_light_only": (lambda tmp: _delta_lit_media("spot"), True),
    "directional_light_only": (lambda tmp: _delta_lit_media("directional"), True),
    "grazing_camera_rays": (lambda tmp: _grazing_medium(), True),
}
VOLUMETRIC = {"volpath_delta": {"type": "volpath_delta"},
              "volpath_raymarch": {"type": "volpath_raymarch", "step_size": 0.02}}


@pytest.fixture(scope="module")
def media_reference():
    """The reference per media case (volpath unless REFERENCES says otherwise; 16 passes),
    made once per module."""
    cache = {}

    def get(case, scene):
        if case not in cache:
            reference = REFERENCES.get(case, {"type": "volpath"})
            cache[case] = estimate(scene, {**reference, "max_depth": DEPTH}, passes=16,
                                   spp=16 if case in DENSE else 64, seed=0)
        return cache[case]
    return get


@pytest.mark.parametrize("case", list(MEDIA_CASES))
@pytest.mark.parametrize("ours", list(VOLUMETRIC))
def test_media_case(ours, case, tmp_path, media_reference):
    build, march_agrees = MEDIA_CASES[case]
    scene = build(tmp_path)
    a = estimate(scene, {**VOLUMETRIC[ours], "max_depth": DEPTH}, passes=8,
                 spp=16 if case in DENSE else 32, seed=1000)
    assert (a.mean >= 0).all()
    if ours == "volpath_raymarch" and not march_agrees:
        return  # finite (asserted by estimate); the furnace test below bounds its energy
    assert_same_expectation(a, media_reference(case, scene), f"{ours}-{case}")


# -- chromatic extinction ratio 1000, where volpath is wrong ----------------------------------
CHROMATIC = [0.01, 0.3, 10.0]   # max / min = 1000


def _chromatic_scene(sigma_t):
    return media_scene(homogeneous(sigma_t, albedo=0.9), sensor=camera(res=RES))


def chromatic_reference() -> stats.Estimate:
    """Channel c of the chromatic image equals the image of a gray medium with
    sigma_t = CHROMATIC[c] (everything else in the scene is gray): three volpath renders.
    Mono: one volpath render of the scene itself (its medium is gray). Spectral variants
    upsample the RGB extinction to a smooth spectrum and the film mixes wavelengths into
    every channel, so the construction fails there: the reference is Mitsuba's
    ``volpathmis`` (spectral MIS over the wavelengths), which passes against the
    channel-wise reference in RGB (test below)."""
    if not mi.is_rgb:
        return estimate(_chromatic_scene(CHROMATIC), {
            "type": "volpath" if mi.is_monochromatic else "volpathmis", "max_depth": DEPTH},
            passes=16, spp=64, seed=10)
    parts = [estimate(_chromatic_scene(s), {"type": "volpath", "max_depth": DEPTH}, passes=16,
                      spp=64, seed=10 + c) for c, s in enumerate(CHROMATIC)]
    return stats.Estimate(mean=np.stack([p.mean[..., c] for c, p in enumerate(parts)], axis=-1),
                          se=np.stack([p.se[..., c] for c, p in enumerate(parts)], axis=-1),
                          passes=16, spp_per_pass=64)


@pytest.fixture(scope="module")
def channelwise_reference():
    return chromatic_reference()


@pytest.mark.parametrize("ours", list(VOLUMETRIC))
def test_chromatic_ratio_1000(ours, channelwise_reference):
    a = estimate(_chromatic_scene(CHROMATIC), {**VOLUMETRIC[ours], "max_depth": DEPTH},
                 passes=8, spp=32, seed=1000)
    assert_same_expectation(a, channelwise_reference, f"{ours}-chromatic_1000")


@pytest.mark.skipif(not mi.is_rgb, reason="checks volpathmis against the per-channel "
                    "reference, which only RGB variants can build (one gray render per "
                    "channel); spectral variants then use volpathmis as their reference")
def test_volpathmis_agrees_with_the_channelwise_reference(channelwise_reference):
    """What makes volpathmis the spectral variants' reference above: in RGB it passes
    the same test as ours (measured: image-mean z -1.21 / -1.33 / 0.80)."""
    b = estimate(_chromatic_scene(CHROMATIC), {"type": "volpathmis", "max_depth": DEPTH},
                 passes=8, spp=32, seed=1000)
    assert_same_expectation(b, channelwise_reference, "volpathmis-chromatic_1000")


@pytest.mark.skipif(mi.is_monochromatic, reason="mono renders the medium's luminance, a "
                    "gray medium, where volpath is correct and is itself the reference")
def test_volpath_is_wrong_on_chromatic_ratio_1000(channelwise_reference):
    """The built-in fails the same test. Measured (16 x 64 spp at 24x24, these seeds):
    40.7% of pixel channels beyond the Sidak |z| of 4.53 (max |z| 30.9), image-mean z
    -38.6 / -30.6 / -11.0 per channel: far too dark. Ours, same test: 0.23% and
    -0.48 / -0.78 / 0.21."""
    b = estimate(_chromatic_scene(CHROMATIC), {"type": "volpath", "max_depth": DEPTH},
                 passes=16, spp=64, seed=1000)
    assert not stats.compare(b, channelwise_reference).passed


# -- furnaces ---------------------------------------------------------------------------------
FURNACES = {
    "homogeneous_g_0.7": lambda tmp: homogeneous(3.0, albedo=1.0, g=0.7),
    "homogeneous_chromatic": lambda tmp: homogeneous([0.05, 1.0, 5.0], albedo=1.0),
    "extinction_1e-4": lambda tmp: homogeneous(1e-4, albedo=1.0),
    "extinction_1e4": lambda tmp: homogeneous(1e4, albedo=1.0),
    "chromatic_1000": lambda tmp: homogeneous(CHROMATIC, albedo=1.0),
    "hg_g_-0.99": lambda tmp: homogeneous(2.0, albedo=1.0, g=-0.99),
    "hg_g_0.99": lambda tmp: homogeneous(2.0, albedo=1.0, g=0.99),
    "grid": lambda tmp: grid(scale=20.0, albedo=1.0),
    "grid_chromatic": lambda tmp: grid(scale=20.0, albedo=1.0, sigma_t=[1.0, 0.3, 0.05]),
    "grid_1e4": lambda tmp: {**HARD_MEDIA["grid_1e4"](tmp), "albedo": 1.0},
    "one_dense_voxel": lambda tmp: {**HARD_MEDIA["one_dense_voxel"](tmp), "albedo": 1.0},
}
#: the ways through a medium that conserve its energy (single scattering only loses it);
#: a march's energy is exact for the marched medium at any step, so also at a step of
#: 0.4, a tenth of the ball (measured 1.0015 +- 0.0014 at 0.4 to 0.05 on the gray grid)
FURNACE_INTEGRATORS = {
    "volpath_delta": {"type": "volpath_delta"},
    "decomposition": {"type": "volpath_delta", "free_flight": "decomposition"},
    "volpath_raymarch": {"type": "volpath_raymarch", "step_size": 0.02},
    "volpath_raymarch_step_0.4": {"type": "volpath_raymarch", "step_size": 0.4},
    "volpath_raymarch_single": {"type": "volpath_raymarch", "mode": "single"},
}
#: homogeneous media are never tracked nor marched: one flight of each kind covers them
HOMOGENEOUS_FURNACE_INTEGRATORS = ("volpath_delta", "volpath_raymarch",
                                   "volpath_raymarch_single")
FURNACE_CASES = [(m, i) for m in FURNACES for i in FURNACE_INTEGRATORS
                 if "grid" in m or "voxel" in m or i in HOMOGENEOUS_FURNACE_INTEGRATORS]


#: Dense albedo-1 media need ~(R / mean free path) scattering events per path. With
#: Mitsuba's roulette (survival capped at 0.95 however bright the path) a path that
#: survives n events carries 0.95^-n: unbiased, but a tail so heavy that sample means
#: come out low. Measured at 16x16 x 64 spp, sigma_t 1e4: 0.79 for volpath_delta and
#: 0.86 for Mitsuba's volpath; 1.00 and 0.99 without roulette. So these furnaces run
#: without roulette (rr_depth 1e6, at 8x8 x 16 spp), where every path ends by leaving.
#: The one dense voxel (1e4) has the same tail on the paths that enter it: volpath_delta
#: at 16x16 x 64 spp, seeds 7-11, gave t = -2.54 / -3.43 / -2.28 / 0.64 / -0.87 with
#: roulette and 1.57 / -0.22 / 0.35 / 0.22 / 1.40 without (the same with hot cells
#: refined: -3.39 ... and 0.42 ...); it passed with roulette by the luck of one stream.
DENSE_FURNACES = ("extinction_1e4", "grid_1e4", "one_dense_voxel")


def _furnace(medium, res):
    return mi.load_dict({
        "type": "scene",
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "ball": {"type": "sphere", "bsdf": {"type": "null"}, "interior": medium},
        "sensor": camera(res=res, fov=30.0)})


@pytest.mark.parametrize("case,ours", FURNACE_CASES, ids=[f"{i}-{m}" for m, i in FURNACE_CASES])
def test_furnace(ours, case, tmp_path):
    """The furnace matrix (integrator x medium): a ball of albedo-1 medium (any density,
    phase function or chromatic extinction) behind a null boundary in a uniform
    environment of radiance 1 neither absorbs nor emits, so every pixel is 1 (t-test per
    channel, alpha 1e-3). Single scattering drops every path after its first scattering
    event, so there the bound is one-sided: mean <= 1 (t < 3.1)."""
    dense = case in DENSE_FURNACES
    scene = _furnace(FURNACES[case](tmp_path), res=8 if dense else 16)
    integrator = {**FURNACE_INTEGRATORS[ours], **({"rr_depth": 10 ** 6} if dense else {})}
    img = render(scene, integrator, seed=7, spp=16 if dense else 64)
    if ours.endswith("single") and mi.is_spectral:
        # losing light at some wavelengths may raise an sRGB channel (the XYZ -> sRGB
        # matrix has negative entries: 1.05 in red for chromatic_1000); the luminance Y
        # weighs every wavelength >= 0, so the bound holds for it
        img = (img @ LUMINANCE)[..., None]
    for c in range(img.shape[-1]):
        res = stats.t_test(img[..., c], 1.0)
        if ours.endswith("single"):
            assert res.t < 3.1, f"{ours} furnace {case} channel {c}: {res.summary()}"
        else:
            assert res.p > 1e-3, f"{ours} furnace {case} channel {c}: {res.summary()}"


@pytest.mark.parametrize("ours", list(VOLUMETRIC))
def test_dense_furnace_with_roulette_keeps_the_bound(ours):
    """With the default roulette the dense furnace's sample mean may fall short of 1
    (heavy tail, above) but never exceed it: one-sided t < 3.1 per channel."""
    img = render(_furnace(FURNACES["extinction_1e4"](None), res=16),
                 VOLUMETRIC[ours], seed=7, spp=64)
    for c in range(img.shape[-1]):
        res = stats.t_test(img[..., c], 1.0)
        assert res.t < 3.1, f"{ours} channel {c}: {res.summary()}"


# -- no NaN/Inf sample, in every configuration -------------------------------------------------
#: Every configuration of our volumetric integrators, and Mitsuba's volpath on our media
CONFIGURATIONS = {
    "delta-track_length": {"type": "volpath_delta", "transmittance": "track_length"},
    "delta-ratio": {"type": "volpath_delta", "transmittance": "ratio"},
    "delta-residual": {"type": "volpath_delta", "transmittance": "residual"},
    "decomposition": {"type": "volpath_delta", "free_flight": "decomposition"},
    "march-multi": {"type": "volpath_raymarch", "step_size": 0.05},
    "march-single": {"type": "volpath_raymarch", "step_size": 0.05, "mode": "single"},
    "march-multi-step-beyond-medium": {"type": "volpath_raymarch", "step_size": 10.0},
    "march-single-step-beyond-medium": {"type": "volpath_raymarch", "step_size": 10.0,
                                        "mode": "single"},
    "march-majorant-steps": {"type": "volpath_raymarch", "step_size": 0.05,
                             "step_mode": "majorant", "step_optical_depth": 0.5},
    "volpath": {"type": "volpath"},
}
#: what differs between configurations only matters in heterogeneous media: homogeneous
#: media are rendered with one configuration of each way through them
HOMOGENEOUS_CONFIGURATIONS = ("delta-residual", "march-multi", "march-single",
                              "march-single-step-beyond-medium")


def _degenerate_sparse(tmp, value: float) -> dict:
    from mitsuba_plugins.grids import gridio
    data = np.zeros((24, 24, 24, 1), np.float32)
    data[11, 12, 13] = value
    gridio.write_vol(tmp / "g.vol", data)
    return grid(filename=str(tmp / "g.vol"), storage="sparse")


FINITE_MEDIA = {**HARD_MEDIA,
                "sparse_grid": lambda tmp: grid(filename=SPARSE, scale=40.0),
                "empty_sparse": lambda tmp: _degenerate_sparse(tmp, 0.0),
                "one_voxel_sparse": lambda tmp: _degenerate_sparse(tmp, 50.0)}
FINITE_CASES = [(m, c) for m in FINITE_MEDIA for c in CONFIGURATIONS
                if (not m.startswith("homogeneous") or c in HOMOGENEOUS_CONFIGURATIONS)
                # Mitsuba's volpath: on our sparse storage (its dense extreme grids cost it
                # ~2e4 null collisions a crossing, and tests/integrators/test_stability.py's z-tests
                # render it there already)
                and (c != "volpath" or "sparse" in m)]


@pytest.mark.parametrize("medium,config", FINITE_CASES,
                         ids=[f"{m}-{c}" for m, c in FINITE_CASES])
def test_no_nan_or_inf_sample(medium, config, tmp_path):
    """Extreme media (extinction 1e-4 and 1e4, a chromatic ratio of 1e8 with a 0 channel,
    empty grids, one dense voxel, sparse storage) in every configuration: no sample is NaN
    or Inf (counted in the kernel; helpers.render asserts the count is 0 and every pixel
    finite) and light gets through (the scene's floor is lit)."""
    scene = media_scene(FINITE_MEDIA[medium](tmp_path), sensor=camera(res=16))
    img = render(scene, {**CONFIGURATIONS[config], "max_depth": 12}, seed=1, spp=16)
    assert img.mean() > 0, (medium, config)



# -- a medium's shape larger than its grid: volpath's underflow (mitsuba3 #336) ------------
#: the grid's density times ``scale``: the global majorant times the chord through the
#: empty part of the cube reaches ~350, beyond float32's exp(-87)
UNDERFLOW_SIGMA = 100.0


def _shape_beyond_grid(medium_kind: str, fitted: bool = False, res: int = RES):
    """A cube [-1, 1]^3 with a null BSDF around a medium whose density is 1 x
    UNDERFLOW_SIGMA on [0, 1]^3 and 0 elsewhere (albedo 0.9, constant environment), as a
    user wraps a grid in a bounding cube: Mitsuba's ``heterogeneous`` medium with a 1^3
    ``gridvolume`` (whose box is [0, 1]^3), or ``grid_medium`` over the whole cube with a
    2^3 grid, nearest lookup, one voxel non-zero. ``fitted``: the cube is [0, 1]^3 itself
    (the same radiance: null interfaces are invisible)."""
    if medium_kind == "heterogeneous":
        medium = {"type": "heterogeneous", "albedo": 0.9, "scale": UNDERFLOW_SIGMA,
                  "sigma_t": {"type": "gridvolume",
                              "grid": mi.VolumeGrid(np.ones((1, 1, 1, 1), np.float32))}}
    else:
        data = np.zeros((2, 2, 2, 1), np.float32)
        data[1, 1, 1] = 1.0
        medium = {"type": "grid_medium", "albedo": 0.9, "scale": UNDERFLOW_SIGMA,
                  "sigma_t": {"type": "gridvolume", "grid": mi.VolumeGrid(data),
                              "filter_type": "nearest",
                              "to_world": T().translate([-1, -1, -1]).scale(2)}}
    box = T().translate([0.5, 0.5, 0.5]).scale(0.5) if fitted else T()
    return mi.load_dict({
        "type": "scene",
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "cube": {"type": "cube", "to_world": box, "bsdf": {"type": "null"}, "interior": medium},
        "sensor": {"type": "perspective", "fov": 30.0,
                   "to_world": T().look_at([5, 3, 5], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}}})


@pytest.fixture(scope="module")
def fitted_reference():
    """volpath where it is right: the cube fitted to the grid's box."""
    return estimate(_shape_beyond_grid("heterogeneous", fitted=True),
                    {"type": "volpath", "max_depth": DEPTH}, passes=8, spp=32, seed=336)


@pytest.mark.parametrize("medium_kind", ["heterogeneous", "grid_medium"])
@pytest.mark.parametrize("ours", list(VOLUMETRIC))
def test_a_shape_beyond_its_grid_stays_right(ours, medium_kind, fitted_reference):
    a = estimate(_shape_beyond_grid(medium_kind), {**VOLUMETRIC[ours], "max_depth": DEPTH},
                 passes=8, spp=32, seed=1336)
    assert_same_expectation(a, fitted_reference, f"{ours}-{medium_kind}-shape_beyond_grid")


def test_volpath_goes_black_beyond_its_grid(fitted_reference):
    """The built-in on the same scene: where a ray crosses the cube but not the grid's box
    its free-flight weight is exp(-majorant t) / exp(-majorant t) with t the whole chord,
    0 / 0 once majorant x t passes ~87: measured at 24x24, 8 x 32 spp, 3.5% of the pixels
    exactly 0 (where the reference is about 1) and the test below fails."""
    b = estimate(_shape_beyond_grid("heterogeneous"), {"type": "volpath", "max_depth": DEPTH},
                 passes=8, spp=32, seed=1336)
    black = float(np.mean(b.mean[..., 0] == 0))
    assert black > 0.01, f"volpath's black pixels: {black:.3%}"
    assert not stats.compare(b, fitted_reference).passed
