"""Volumes as studios ship them (issue 27): fire (a temperature grid becomes blackbody
emission, mitsuba_plugins.grids.blackbody) and colour grids (``albedo_grid``).

* The normalised Planck spectrum against pbrt-v4's own formula and constants.
* The RGB / luminance table against an independent integration (``colour-science``: its
  CIE 1931 tables, Planck's law and sRGB matrix): chromaticities r/g and b/g within 1%
  from 1000 K to 10000 K.
* The kernel's values in the active variant against those.
* Renders: an absorbing slab at one temperature against the analytic radiance (t-test per
  channel), a plume stored sparse against dense (docs/validation.md's per-pixel test).
* An albedo colour grid renders what the same constant albedo renders.
* Refusals, each naming the parameter.
"""
from __future__ import annotations

import colour
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import (SMOKE as SMOKE_VOL, assert_same_expectation, camera, emissive_slab, estimate, make_vdb,
                     media_scene)
from mitsuba_plugins.grids import blackbody
from mitsuba_plugins.tools import stats

TEMPERATURES = np.arange(1000.0, 10001.0, 500.0)


def pbrt_blackbody(lam_nm, t):
    """pbrt-v4's ``Blackbody(lambda, T)`` (its float constants), normalised as its
    ``BlackbodySpectrum`` does: divided by the value at ``lambdaMax = 2.8977721e-3 / T``."""
    c, h, kb = 299792458.0, 6.62606957e-34, 1.3806488e-23

    def planck(lam_m):
        return 2 * h * c * c / (lam_m ** 5 * (np.exp(h * c / (lam_m * kb * t)) - 1))
    return planck(np.asarray(lam_nm) * 1e-9) / planck(2.8977721e-3 / t)


def independent_xyz(t: float) -> np.ndarray:
    """XYZ (Y of a flat spectrum of 1 = 1) of the peak-normalised blackbody, by
    colour-science on its own 1 nm CIE 1931 table."""
    shape = colour.SpectralShape(360, 830, 1)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    sd = colour.sd_blackbody(t, shape)
    peak = float(np.ravel(colour.colorimetry.planck_law(2.897771955e-3 / t, t))[0]) * 1e-9
    return colour.sd_to_XYZ(sd / peak, cmfs, method="Integration") / 100.0


def independent_rgb(t: float) -> np.ndarray:
    return colour.XYZ_to_RGB(independent_xyz(t), colour.RGB_COLOURSPACES["sRGB"],
                             apply_cctf_encoding=False)


def close_ratio(ours: float, theirs: float, rel: float = 0.01) -> bool:
    """Relative agreement; near a zero crossing (|ratio| < 0.01: b/g around 1900 K)
    absolute 1e-4."""
    return abs(ours - theirs) <= max(rel * abs(theirs), 1e-4)


def test_normalisation_is_pbrts():
    lam = np.linspace(360.0, 830.0, 471)
    for t in (150.0, 500.0, 1000.0, 3000.0, 6500.0, 20000.0):
        ours = blackbody.normalised(lam, t)
        np.testing.assert_allclose(ours, pbrt_blackbody(lam, t), rtol=2e-5, atol=1e-300)
        peak = blackbody.WIEN / t
        assert blackbody.normalised(peak, t) == pytest.approx(1.0, abs=1e-12)
        assert ours.max() <= 1.0 + 1e-12
    assert np.all(blackbody.normalised(lam, blackbody.CUTOFF) == 0.0)   # pbrt: T <= 100 K


def test_table_chromaticity_against_independent_integration():
    """r/g and b/g of the (unclamped) linear sRGB table and the luminance within 1% of
    colour-science's integration, 1000 K to 10000 K every 500 K."""
    table_t, rgb = blackbody.rgb_table()
    _, xyz = blackbody.xyz_table()
    log_t = np.log(table_t)
    for t in TEMPERATURES:
        ours = np.array([np.interp(np.log(t), log_t, rgb[:, c]) for c in range(3)])
        theirs = independent_rgb(t)
        assert close_ratio(ours[0] / ours[1], theirs[0] / theirs[1]), (t, ours, theirs)
        assert close_ratio(ours[2] / ours[1], theirs[2] / theirs[1]), (t, ours, theirs)
        y = np.interp(np.log(t), log_t, xyz[:, 1])
        assert y == pytest.approx(independent_xyz(t)[1], rel=0.01), t


def kernel_values(temperatures, wavelengths=None) -> np.ndarray:
    """``blackbody.spectrum`` in the active variant, (n, channels)."""
    t = mi.Float(np.asarray(temperatures, np.float32))
    if wavelengths is not None:
        lam = mi.Spectrum(*[mi.Float(np.full(len(temperatures), w, np.float32))
                            for w in wavelengths])
    else:
        lam = dr.zeros(mi.Spectrum, len(temperatures))
    value = blackbody.spectrum(t, lam)
    return np.stack([np.array(value[c]) for c in range(dr.size_v(mi.UnpolarizedSpectrum))],
                    axis=-1)


def test_kernel_values():
    """What a render evaluates: linear sRGB clamped at 0 (RGB variants, within 1% of the
    largest channel of colour-science's values), luminance (mono), Planck's law at the
    path's wavelengths (spectral, 1e-4); 0 at and below 100 K."""
    cold = kernel_values([0.0, 50.0, 100.0])
    assert np.all(cold == 0.0)
    if mi.is_spectral:
        waves = (380.0, 520.0, 650.0, 800.0)
        got = kernel_values(TEMPERATURES, waves)
        want = blackbody.normalised(np.array(waves)[None, :], TEMPERATURES[:, None])
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-30)
        return
    got = kernel_values(TEMPERATURES)
    for t, value in zip(TEMPERATURES, got):
        if mi.is_monochromatic:
            assert value[0] == pytest.approx(independent_xyz(t)[1], rel=0.01), t
            continue
        want = np.maximum(independent_rgb(t), 0.0)
        assert np.all(np.abs(value - want) <= 0.01 * want.max()), (t, value, want)
        assert np.all(value >= 0.0)


def expected_colour(t: float) -> np.ndarray:
    """The colour a film records for the peak-normalised blackbody (RGB or Y)."""
    if mi.is_monochromatic:
        return independent_xyz(t)[1:2]
    return independent_rgb(t)


def fire_vdb(path, density, temperature, voxel=1.0 / 16):
    make_vdb(path, """
        for name, values in (("density", density), ("temperature", temperature)):
            g = vdb.FloatGrid(); g.name = name
            g.copyFromArray(values); g.transform = vdb.createLinearTransform(voxel)
            grids.append(g)
    """.replace("voxel", repr(voxel)), density=density, temperature=temperature)
    return str(path)


@pytest.mark.parametrize("interpolation", ["trilinear", "nearest"])
@pytest.mark.parametrize("value, offset", [(30.0, 5.0), (-20.0, -45.0)])
def test_uniform_fire_slab_matches_the_analytic_radiance(tmp_path, interpolation, value,
                                                         offset):
    """An absorbing slab of density 1 at one temperature (grid value 30, offset 5, scale
    100 K: 2500 K, inside the sRGB gamut), seen through its 2 units: Le B(T) (1 -
    exp(-sigma_t 2)) per channel (t-test, 256 spp). In spectral variants the film
    integrates Planck's law over the wavelengths: the same colour. A negative grid that
    the offset makes positive (-20, offset -45) is the same fire (it was refused: issue
    46)."""
    # 12 voxels of 0.25 centred on the slab: a .vdb's voxel centres sit at the index
    # positions and trilinear lookups blend with the background 0 beyond the outer
    # centres, so the grid overhangs the cube [-1, 1]^3 by a voxel and a half
    n, voxel = 12, 0.25
    path = fire_vdb(tmp_path / "uniform.vdb", np.ones((n, n, n), np.float32),
                    np.full((n, n, n), value, np.float32), voxel=voxel)
    sigma, Le = 0.7, 3.0
    shift = -(n - 1) * voxel / 2
    scene = emissive_slab(
        Le, filename=path, scale=sigma, temperature_grid="temperature",
        temperature_offset=offset, temperature_scale=100.0, interpolation=interpolation,
        to_world=mi.ScalarTransform4f().translate([shift] * 3))
    img = np.array(mi.render(scene, integrator=mi.load_dict({"type": "volpath_delta"}),
                             seed=3, spp=256))
    want = Le * expected_colour(2500.0) * (1.0 - np.exp(-2.0 * sigma))
    for c in range(len(want)):
        res = stats.t_test(img[..., c], want[c])
        assert res.p > 1e-3, f"channel {c}: expected {want[c]:.5f}, {res.summary()}"


@pytest.fixture(scope="module")
def plume(tmp_path_factory):
    """A smoke ball with a hot core: density 0..2, temperature up to 2400 K (grid values
    in hundreds of kelvin), half of the box empty."""
    n = 24
    z, y, x = np.meshgrid(*(np.linspace(-1, 1, n),) * 3, indexing="ij")
    r2 = x * x + (y + 0.3) ** 2 + z * z
    density = np.where(r2 < 0.5, 2.0 * np.exp(-3.0 * r2), 0.0).astype(np.float32)
    temperature = np.where(r2 < 0.25, 24.0 * (1.0 - r2 / 0.25), 0.0).astype(np.float32)
    return fire_vdb(tmp_path_factory.mktemp("fire") / "plume.vdb", density, temperature,
                    voxel=2.0 / n)


def plume_scene(path, storage):
    return media_scene({"type": "grid_medium", "filename": path, "storage": storage,
                        "scale": 3.0, "albedo": 0.6, "temperature_grid": "temperature",
                        "temperature_scale": 100.0, "emission": 2.0,
                        "to_world": mi.ScalarTransform4f().translate([-1, -1, -1])},
                       sensor=camera(res=16), env=0.05)


def test_fire_sparse_equals_dense(plume):
    """The plume stored sparse and dense renders the same image (per-pixel test against
    an independent render) and glows: its brightest pixel is well above the lit smoke."""
    integrator = {"type": "volpath_delta", "max_depth": 6}
    sparse = estimate(plume_scene(plume, "sparse"), integrator, passes=8, spp=32, seed=0)
    dense = estimate(plume_scene(plume, "dense"), integrator, passes=8, spp=32, seed=100)
    assert_same_expectation(sparse, dense, "fire_sparse_dense")
    assert sparse.mean.max() > 0.1


@pytest.mark.parametrize("params, message", [
    (dict(temperature_scale=0.0), "'temperature_scale' = 0.0 is invalid; allowed: a finite "
                                  "number > 0"),
    (dict(temperature_scale=1e5), "allowed: at most 100000 K"),
    (dict(emission_grid="temperature"), "give one of them"),
    (dict(temperature_grid="missing"), "missing"),
])
def test_bad_fire_parameters_are_refused(plume, params, message):
    desc = {"type": "grid_medium", "filename": plume, "temperature_grid": "temperature",
            **params}
    with pytest.raises(Exception, match=message):
        mi.load_dict(desc)


def test_fire_parameters_need_a_temperature_grid(plume, tmp_path):
    with pytest.raises(Exception, match="'temperature_offset' applies to a "
                                                   "'temperature_grid'"):
        mi.load_dict({"type": "grid_medium", "filename": plume, "temperature_offset": 3.0})
    npy = tmp_path / "d.npy"
    np.save(npy, np.ones((4, 4, 4), np.float32))
    with pytest.raises(Exception, match="'temperature_grid' selects a grid of a .vdb file"):
        mi.load_dict({"type": "grid_medium", "filename": str(npy),
                      "temperature_grid": "temperature"})


# -- colour grids ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def coloured(tmp_path_factory):
    """A smoke ball with a uniform vec3 ``Cd`` grid (0.2, 0.5, 0.8), a float ``tint`` of
    0.5 on a grid of another resolution and placement, and ``bright``, 1.6."""
    n = 16
    z, y, x = np.meshgrid(*(np.linspace(-1, 1, n),) * 3, indexing="ij")
    density = np.where(x * x + y * y + z * z < 0.8, 2.0, 0.0).astype(np.float32)
    cd = np.broadcast_to(np.array([0.2, 0.5, 0.8], np.float32), (n, n, n, 3)).copy()
    path = tmp_path_factory.mktemp("colour") / "coloured.vdb"
    make_vdb(path, f"""
        g = vdb.FloatGrid(); g.name = "density"; g.copyFromArray(density)
        g.transform = vdb.createLinearTransform({2.0 / n!r}); grids.append(g)
        c = vdb.Vec3SGrid(); c.name = "Cd"; c.copyFromArray(cd)
        c.transform = vdb.createLinearTransform({2.0 / n!r}); grids.append(c)
        t = vdb.FloatGrid(); t.name = "tint"; t.copyFromArray(np.full((40, 40, 40), 0.5, np.float32))
        t.transform = vdb.createLinearTransform(matrix=[[0.08, 0, 0, 0], [0, 0.08, 0, 0],
                                                        [0, 0, 0.08, 0], [-0.6, -0.6, -0.6, 1]])
        grids.append(t)
        b = vdb.FloatGrid(); b.name = "bright"; b.copyFromArray(np.full((8, 8, 8), 1.6, np.float32))
        grids.append(b)
    """, density=density, cd=cd)
    return str(path)


def coloured_scene(path, **params):
    return media_scene({"type": "grid_medium", "filename": path, "scale": 4.0,
                        "to_world": mi.ScalarTransform4f().translate([-1, -1, -1]), **params},
                       sensor=camera(res=16))


@pytest.mark.parametrize("grid, albedo, constant", [
    ("Cd", None, [0.2, 0.5, 0.8]),
    ("tint", [0.4, 0.9, 0.6], [0.2, 0.45, 0.3]),
])
def test_albedo_grid_renders_the_constant_albedo(coloured, grid, albedo, constant):
    """A uniform albedo grid (vec3 ``Cd``; a float grid of its own placement times an RGB
    ``albedo``) renders what the same constant albedo renders (per-pixel test)."""
    integrator = {"type": "volpath_delta", "max_depth": 8}
    extra = {} if albedo is None else {"albedo": {"type": "rgb", "value": albedo}}
    ours = estimate(coloured_scene(coloured, albedo_grid=grid, **extra), integrator,
                    passes=8, spp=32, seed=0)
    ref = estimate(coloured_scene(coloured, albedo={"type": "rgb", "value": constant}),
                   integrator, passes=8, spp=32, seed=100)
    assert_same_expectation(ours, ref, f"albedo_grid_{grid}")


def test_albedo_grid_range_is_checked(coloured):
    with pytest.raises(Exception, match="'albedo' x 'albedo_grid' reach 1.6"):
        mi.load_dict({"type": "grid_medium", "filename": coloured, "albedo_grid": "bright"})
    with pytest.raises(Exception, match="'albedo_grid' selects a grid of a .vdb"):
        mi.load_dict({"type": "grid_medium", "albedo_grid": "Cd",
                      "filename": str(SMOKE_VOL)})


def test_fire_scene_renders_a_flame():
    """scenes/fire.xml (the half-float .vdb of make_fire.py): finite, no NaN/Inf sample,
    and its brightest pixel is a flame's colour, red > green > blue (mono: bright)."""
    from helpers import load, render
    img = render(load("fire", res=24, spp=16))
    brightest = img.reshape(-1, img.shape[-1])[np.argmax(img.sum(axis=-1))]
    if mi.is_monochromatic:
        assert brightest[0] > 0.1, brightest
        return
    r, g, b = brightest[:3]
    assert r > g > b and r > 0.3, (r, g, b)
