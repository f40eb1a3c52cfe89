"""grid_medium: a drop-in for heterogeneous (bit-identical under Mitsuba's volpath where
the random numbers agree, z-tested where the arithmetic differs), its parameters, bad
input, traversal and emission."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import (LUMINANCE, SCENES, assert_same_expectation, estimate, load, medium_at,
                     render)
from mitsuba_plugins.grids import gridio

RES, SPP = 32, 16


def _scene(medium: dict, shape_to_world=None, res=RES, spp=SPP, max_depth=8):
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": max_depth},
        "env": {"type": "constant", "radiance": 0.3},
        "light": {"type": "point", "position": [2.0, 3.0, 2.0], "intensity": 20.0},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at([0.5, 1.0, 3.5], [0.5, 0.5, 0.5],
                                                              [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "box": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium,
                "to_world": shape_to_world or mi.ScalarTransform4f().translate(
                    [0.5, 0.5, 0.5]).scale(0.5)},
    })


def _render(scene, seed=3):
    return render(scene, seed=seed)


@pytest.fixture(scope="module")
def grids(tmp_path_factory):
    root = tmp_path_factory.mktemp("grids")
    rng = np.random.default_rng(0)
    gray = (rng.random((12, 10, 14)) ** 3).astype(np.float32)
    gray[2:4, 3:5, 4:6] = 3.0
    rgb = gray[..., None] * np.float32([1.0, 0.3, 0.05])
    gridio.write_vol(root / "gray.vol", gray)
    np.save(root / "gray.npy", gray)
    gridio.write_vol(root / "rgb.vol", rgb)
    gridio.write_vol(root / "boxed.vol", gray, ((-0.2, 0.1, 0.0), (1.1, 0.9, 1.3)))
    albedo = np.clip(rng.random((6, 6, 6)), 0, 1).astype(np.float32)
    gridio.write_vol(root / "albedo.vol", albedo)
    return root


TRANSFORMS = {
    "identity": mi.ScalarTransform4f(),
    "rotated_scaled": mi.ScalarTransform4f().translate([0.5, 0.5, 0.5]).rotate(
        [1, 1, 0], 30).scale([1.2, 0.8, 1.0]).translate([-0.5, -0.5, -0.5]),
}
INTERP = {"trilinear": "trilinear", "nearest": "nearest"}


@pytest.mark.parametrize("transform", sorted(TRANSFORMS))
@pytest.mark.parametrize("interpolation", sorted(INTERP))
@pytest.mark.parametrize("grid", ["gray.vol", "rgb.vol"])
def test_filename_matches_heterogeneous_exactly(grids, transform, interpolation, grid):
    """Same lookups, same majorant, same random numbers: the same image."""
    tw = TRANSFORMS[transform]
    shape_tw = tw @ mi.ScalarTransform4f().translate([0.5, 0.5, 0.5]).scale(0.5)
    common = {"scale": 5.0, "albedo": {"type": "rgb", "value": [0.9, 0.7, 0.5]},
              "phase": {"type": "hg", "g": 0.4}, "has_spectral_extinction": True}
    ours = _scene(dict(common, type="grid_medium", filename=str(grids / grid),
                       interpolation=interpolation, to_world=tw), shape_tw)
    theirs = _scene(dict(common, type="heterogeneous", sigma_t={
        "type": "gridvolume", "filename": str(grids / grid), "to_world": tw,
        "filter_type": interpolation}), shape_tw)
    if grid == "rgb.vol" and not mi.is_rgb:
        # spectral: upsampled RGB, mono: its luminance. heterogeneous's majorant is
        # scale x the stored maximum there, ours bounds the values (issue 24), so the
        # random numbers part: the same expectation
        a = estimate(ours, {"type": "volpath", "max_depth": 8}, passes=8, spp=16, seed=1000)
        b = estimate(theirs, {"type": "volpath", "max_depth": 8}, passes=8, spp=32, seed=0)
        assert_same_expectation(a, b, f"grid_medium_rgb_{interpolation}_{transform}")
        return
    a, b = _render(ours), _render(theirs)
    assert np.abs(a - b).max() <= 1e-6 * max(1.0, b.max())


def test_nested_volume_is_a_drop_in(grids):
    """A heterogeneous scene with only the type name changed renders identically."""
    medium = {"sigma_t": {"type": "gridvolume", "filename": str(grids / "rgb.vol"),
                          "filter_type": "nearest"},
              "albedo": {"type": "gridvolume", "filename": str(grids / "albedo.vol")},
              "scale": 4.0, "phase": {"type": "hg", "g": -0.3}}
    a = _render(_scene(dict(medium, type="grid_medium")))
    b = _render(_scene(dict(medium, type="heterogeneous")))
    assert np.array_equal(a, b)


@pytest.mark.parametrize("integrator", ["volpath", "volpath_delta", "volpath_raymarch"])
def test_nested_rgb_constant_is_chromatic(integrator):
    """sigma_t = an rgb constvolume (which reports 0 channels): chromatic, and its
    minorant the smallest channel. As gray, volpath and volpath_raymarch rendered the
    green of (1, 0.2, 1) 14-24 sigma off heterogeneous; with the largest channel as
    minorant, decomposition tracking rendered it 10% dark."""
    from helpers import camera, media_scene
    sigma_t = {"type": "constvolume", "value": {"type": "rgb", "value": [1.0, 0.2, 1.0]}}
    common = {"scale": 2.0, "albedo": 0.8, "sigma_t": sigma_t}
    medium = mi.load_dict(dict(common, type="grid_medium"))
    chromatic = not mi.is_monochromatic      # mono: one channel, the luminance
    assert medium.has_spectral_extinction() == chromatic and medium.is_chromatic == chromatic
    if chromatic:
        assert float(medium.majorant_grid.minorants.numpy().min()) <= 2.0 * 0.2
    a = estimate(media_scene(dict(common, type="grid_medium"), sensor=camera(res=16)),
                 {"type": integrator, "max_depth": 8}, passes=16, spp=64, seed=1000)
    b = estimate(media_scene(dict(common, type="heterogeneous"), sensor=camera(res=16)),
                 {"type": "volpath", "max_depth": 8}, passes=16, spp=128, seed=0)
    assert_same_expectation(a, b, f"grid_medium_nested_constant_{integrator}")


@pytest.mark.parametrize("start, edit", [(1.0, [1.0, 0.3, 0.05]), ([1.0, 0.3, 0.05], 1.0)])
def test_editing_sigma_t_updates_chromaticity(start, edit):
    """A traversed sigma_t factor edited from gray to chromatic (and back) renders what a
    medium loaded with the new factor renders, bit for bit, with the same flags. The
    flags were set at load only: the edited gray-to-chromatic medium stayed gray (0.10 off
    at 16 spp). The majorant cells are given: chosen automatically, an edit keeps the
    load's choice (an optimisation loop compiles no new kernel) while a fresh load may
    choose others (then the renders differ by the numbers drawn: spectral variants)."""
    from helpers import SMOKE, camera, media_scene

    def scene(factor):
        return media_scene({"type": "grid_medium", "filename": SMOKE, "scale": 4.0,
                            "sigma_t": factor, "majorant_resolution": 16,
                            "to_world": mi.ScalarTransform4f().translate(
                                [-0.5, -0.5, -0.5])}, sensor=camera(res=16))

    def medium(sc):
        return next(s.interior_medium() for s in sc.shapes() if s.interior_medium())

    edited, fresh = scene(start), scene(edit)
    params = mi.traverse(edited)
    key = next(k for k in params.keys() if k.endswith("interior_medium.sigma_t"))
    params[key] = mi.Color3f(edit)
    params.update()
    assert medium(edited).is_chromatic == medium(fresh).is_chromatic
    assert medium(edited).has_spectral_extinction() == medium(fresh).has_spectral_extinction()
    a = render(edited, {"type": "volpath_delta"}, spp=16, seed=1)
    b = render(fresh, {"type": "volpath_delta"}, spp=16, seed=1)
    assert np.array_equal(a, b)


@pytest.mark.parametrize("name", ["smoke", "sparse"])
def test_scene_twins_swap_type_name(name):
    """Equal up to float rounding: for a gray grid grid_medium reports
    has_spectral_extinction = false (heterogeneous always says true), which changes
    volpath's arithmetic, not its random numbers."""
    xml = (SCENES / f"{name}_heterogeneous.xml").read_text()
    swapped = xml.replace('type="heterogeneous"', 'type="grid_medium"')
    swapped = swapped.replace('value="data/', f'value="{SCENES}/data/')
    a = _render(mi.load_string(swapped, res="24", spp="8"))
    b = _render(load(f"{name}_heterogeneous", res=24, spp=8))
    assert np.allclose(a, b, rtol=1e-5, atol=1e-6)


def test_npy_equals_vol(grids):
    a = _render(_scene({"type": "grid_medium", "filename": str(grids / "gray.vol"),
                        "scale": 5.0}))
    b = _render(_scene({"type": "grid_medium", "filename": str(grids / "gray.npy"),
                        "scale": 5.0}))
    assert np.array_equal(a, b)


def test_use_grid_bbox_places_the_grid_like_gridvolume(grids):
    tw = mi.ScalarTransform4f().rotate([0, 1, 0], 20)
    ours = mi.load_dict({"type": "grid_medium", "filename": str(grids / "boxed.vol"),
                         "use_grid_bbox": True, "to_world": tw})
    theirs = mi.load_dict({"type": "gridvolume", "filename": str(grids / "boxed.vol"),
                           "use_grid_bbox": True, "to_world": tw})
    assert np.allclose(np.array(ours.bbox.min), np.array(theirs.bbox().min), atol=1e-5)
    assert np.allclose(np.array(ours.bbox.max), np.array(theirs.bbox().max), atol=1e-5)
    rng = np.random.default_rng(2)
    p = rng.uniform(-0.5, 1.5, (5000, 3)).astype(np.float32)
    mei = dr.zeros(mi.MediumInteraction3f, 5000)
    mei.p = mi.Point3f(*(mi.Float(p[:, i]) for i in range(3)))
    a = np.array(ours.eval_sigma_t(mei))[0]
    b = np.array(theirs.eval(mei))[0]
    assert np.allclose(a, b, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("name", ["smoke", "chromatic"])
def test_scenes_agree_with_twins_statistically(name):
    """Different arithmetic (default gray flags; multiplier vs premultiplied grid):
    Welch z-test, Sidak-corrected, 8 passes each, independent seeds. At this size a
    2% darkening of either image fails with image-mean |z| > 13 (measured)."""
    ours = load(name, res=32, spp=64, max_depth=6)
    theirs = load(f"{name}_heterogeneous", res=32, spp=64, max_depth=6)
    integ = {"type": "volpath", "max_depth": 6}
    a = estimate(ours, integ, passes=8, spp=64, seed=100)
    b = estimate(theirs, integ, passes=8, spp=64, seed=900)
    assert_same_expectation(a, b, f"grid_medium_{name}")


def test_gray_grid_reports_gray_extinction(grids):
    gray = mi.load_dict({"type": "grid_medium", "filename": str(grids / "gray.vol")})
    tinted = mi.load_dict({"type": "grid_medium", "filename": str(grids / "gray.vol"),
                           "sigma_t": [1.0, 0.5, 0.1]})
    rgb = mi.load_dict({"type": "grid_medium", "filename": str(grids / "rgb.vol")})
    assert not gray.has_spectral_extinction() and not gray.is_chromatic
    assert tinted.has_spectral_extinction() and rgb.has_spectral_extinction()
    assert not gray.is_homogeneous()


def test_global_majorant_is_gray_max(grids):
    m = mi.load_dict({"type": "grid_medium", "filename": str(grids / "gray.vol"),
                      "scale": 2.0, "sigma_t": [1.0, 4.0, 0.5]})
    mei = dr.zeros(mi.MediumInteraction3f, 1)
    maj = np.array(m.get_majorant(mei)).ravel()
    assert np.all(maj == maj[0])                    # gray: one value for every channel
    if mi.is_rgb:
        assert np.allclose(maj, 2.0 * 3.0 * 4.0)
    elif mi.is_monochromatic:                       # the factor's luminance
        assert np.isclose(maj[0], 2.0 * 3.0 * (LUMINANCE @ [1.0, 4.0, 0.5]),
                          rtol=1e-5)
    else:
        # the upsampled factor's peak over the visible range, read at the voxel of value 3
        # (its centre: no blending) at 4096 wavelengths: a bound within 1%
        from mitsuba_plugins.grids.spectra import probe_wavelengths
        mei = dr.zeros(mi.MediumInteraction3f, 1024)
        mei.wavelengths = probe_wavelengths(1024)
        mei.p = mi.Point3f(4.5 / 14, 3.5 / 10, 2.5 / 12)
        peak = float(np.max(np.array(m.eval_sigma_t(mei))))
        assert peak <= maj[0] <= 1.01 * peak


def test_traverse_and_parameters_changed(grids):
    scene = _scene({"type": "grid_medium", "filename": str(grids / "gray.vol"),
                    "scale": 2.0, "emission": [1.0, 2.0, 3.0]})
    params = mi.traverse(scene)
    medium = scene.shapes()[0].interior_medium()
    key = "box.interior_medium"
    assert {f"{key}.data", f"{key}.scale", f"{key}.sigma_t"} <= set(params.keys())
    params[f"{key}.scale"] = 4.0
    params.update()
    assert float(medium.global_majorant[0]) == pytest.approx(12.0)
    data = np.array(params[f"{key}.data"])
    data[:] = 0.0
    data[0, 0, 0, 0] = 1.0
    params[f"{key}.data"] = mi.TensorXf(data)
    params.update()
    assert float(medium.global_majorant[0]) == pytest.approx(4.0)
    assert medium.majorant_grid.empty_fraction() > 0.5
    img = _render(scene)
    data[0, 0, 0, 0] = np.nan
    params[f"{key}.data"] = mi.TensorXf(data)
    with pytest.raises(Exception, match="parameter 'data' holds 1 non-finite"):
        params.update()
    # emission is exposed to integrators as radiance
    assert medium.has_emission
    mei = dr.zeros(mi.MediumInteraction3f, 1)
    if mi.is_rgb:
        assert np.allclose(np.array(medium.get_radiance(mei)).ravel(), [1.0, 2.0, 3.0])
    elif mi.is_monochromatic:
        assert np.allclose(np.array(medium.get_radiance(mei)).ravel(),
                           LUMINANCE @ [1.0, 2.0, 3.0], rtol=1e-5)
    else:   # an emitter's rule: d65 times the upsampled colour
        from mitsuba_plugins.grids.spectra import probe_wavelengths
        mei = dr.zeros(mi.MediumInteraction3f, 64)
        si = dr.zeros(mi.SurfaceInteraction3f, 64)
        mei.wavelengths = si.wavelengths = probe_wavelengths(64)
        d65 = mi.load_dict({"type": "d65", "color": [1.0, 2.0, 3.0]})
        assert np.allclose(np.array(medium.get_radiance(mei)), np.array(d65.eval(si)),
                           rtol=1e-5)
    assert img.shape == (RES, RES, 1 if mi.is_monochromatic else 3)


def test_emission_grid_and_absent(grids):
    m = mi.load_dict({"type": "grid_medium", "filename": str(grids / "gray.vol"),
                      "emission": {"type": "gridvolume",
                                   "filename": str(grids / "albedo.vol")}})
    plain = mi.load_dict({"type": "grid_medium", "filename": str(grids / "gray.vol")})
    mei = dr.zeros(mi.MediumInteraction3f, 1)
    mei.p = mi.Point3f(0.5, 0.5, 0.5)
    assert m.has_emission and float(np.array(m.get_radiance(mei))[0, 0]) > 0
    assert not plain.has_emission
    assert np.all(np.array(plain.get_radiance(mei)) == 0)


BAD = {
    "negative scale": ({"scale": -1.0}, "'scale' = -1"),
    "albedo above 1": ({"albedo": 1.5}, "'albedo'"),
    "negative albedo": ({"albedo": [0.5, -0.1, 0.5]}, "'albedo'"),
    "negative multiplier": ({"sigma_t": [1.0, -2.0, 1.0]}, "'sigma_t'"),
    "nan multiplier": ({"sigma_t": float("nan")}, "'sigma_t'"),
    "unknown parameter": ({"density": 1.0}, "unknown parameter 'density'"),
    "interpolation": ({"interpolation": "cubic"}, "'interpolation' = 'cubic'"),
    "majorant_resolution": ({"majorant_resolution": 0}, "'majorant_resolution' = 0"),
    "use_grid_bbox on npy": ({"filename": "gray.npy", "use_grid_bbox": True}, "use_grid_bbox"),
    "missing file": ({"filename": "nope.vol"}, "nope.vol': file does not exist"),
    "negative emission": ({"emission": -1.0}, "'emission'"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_parameters(grids, case):
    props, message = BAD[case]
    spec = {"type": "grid_medium", "filename": str(grids / "gray.vol")}
    spec.update(props)
    if "filename" in props:
        spec["filename"] = str(grids / props["filename"])
    with pytest.raises(Exception, match=message):
        mi.load_dict(spec)


def test_bad_nested_and_file_only_parameters(grids, tmp_path):
    with pytest.raises(Exception, match="'interpolation' applies to a 'filename' grid"):
        mi.load_dict({"type": "grid_medium", "interpolation": "nearest",
                      "sigma_t": {"type": "gridvolume", "filename": str(grids / "gray.vol")}})
    with pytest.raises(Exception, match="albedo: value 3 above 1"):
        mi.load_dict({"type": "grid_medium", "filename": str(grids / "gray.vol"),
                      "albedo": {"type": "gridvolume", "filename": str(grids / "gray.vol")}})
    bad = np.ones((4, 4, 4), np.float32)
    bad[1, 2, 3] = -1.0
    np.save(tmp_path / "neg.npy", bad)
    with pytest.raises(Exception, match="neg.npy.*negative value -1"):
        mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / "neg.npy")})


def test_xml_error_reaches_the_user_as_one_line(grids):
    from mitsuba_plugins.tools.cli import user_message
    xml = f"""<scene version="3.0.0"><shape type="cube"><bsdf type="null"/>
        <medium type="grid_medium" name="interior">
        <string name="filename" value="{grids / 'gray.vol'}"/>
        <float name="scale" value="-3"/></medium></shape></scene>"""
    with pytest.raises(Exception) as info:
        mi.load_string(xml)
    assert user_message(info.value).startswith("grid_medium: parameter 'scale' = -3.0")


def test_a_scene_renders_at_several_sample_counts():
    """A multiplier with a 0 channel (sigma_t = (1, 1e-4, 0)) was a literal that Dr.Jit
    folded into a constant of the first render's width: the same scene rendered again at
    another spp failed ("operands have incompatible sizes")."""
    from helpers import camera, grid, media_scene
    scene = media_scene(grid(scale=20.0, sigma_t=[1.0, 1e-4, 0.0]), sensor=camera(res=8))
    for name in ("volpath_delta", "volpath_raymarch"):
        for spp in (8, 16):
            assert np.all(np.isfinite(render(scene, {"type": name, "max_depth": 4}, spp=spp)))



@pytest.mark.parametrize("storage", ["dense", "sparse"])
@pytest.mark.parametrize("key, bad, message", [
    ("data", np.nan, "parameter '{k}' holds 1 non-finite value(s) (NaN or Inf); allowed: "
                     "finite values >= 0. The previous values are kept"),
    ("data", -1.0, "parameter '{k}' holds 1 value(s) below 0 (smallest -1); allowed: "),
    ("scale", np.inf, "parameter 'scale' = inf is invalid; allowed: a finite number >= 0 "
                      "(the previous value 2 is kept)"),
    ("sigma_t", np.nan, "parameter 'sigma_t' = [nan, 1.0, 1.0] is invalid"),
])
def test_a_refused_edit_names_the_parameter_and_params_holds_what_renders(
        grids, storage, key, bad, message):
    """Issue 46: a NaN put through ``params.update()`` was refused naming the grid *file*,
    and ``params`` kept the NaN while renders used the old data. The message names the
    parameter; ``params`` and the renders hold the previous values."""
    scene = _scene({"type": "grid_medium", "filename": str(grids / "gray.vol"),
                    "scale": 2.0, "storage": storage})
    params = mi.traverse(scene)
    prefix = "box.interior_medium"
    grid_key = f"{prefix}.{'data' if storage == 'dense' else 'bricks'}"
    name = {"data": grid_key, "scale": f"{prefix}.scale", "sigma_t": f"{prefix}.sigma_t"}[key]
    before = np.array(params[name]).copy()
    img = _render(scene)
    edited = before.copy().astype(np.float32)
    edited.reshape(-1)[-1 if key != "data" else np.flatnonzero(edited)[0]] = bad
    if key == "sigma_t":
        edited = np.array([[bad], [1.0], [1.0]], np.float32)
    params[name] = type(params[name])(edited.reshape(before.shape) if key == "data" else
                                      edited.ravel()[0] if key == "scale" else edited)
    with pytest.raises(Exception) as error:
        params.update()
    text = str(error.value).splitlines()[-1]
    assert message.format(k=grid_key.rsplit(".", 1)[1]) in text, text
    np.testing.assert_array_equal(np.array(params[name]), before)
    assert np.array_equal(_render(scene), img)


@pytest.mark.parametrize("storage", ["dense", "sparse"])
def test_tiny_negatives_are_set_to_zero_with_a_warning(tmp_path, storage):
    """Issue 46: one voxel of -1e-6 (common in simulation output) made a grid unusable.
    Values in [-1e-4, 0) are set to 0 with one warning saying how many; the medium then
    equals the same grid with zeros there; -0.01 is still refused."""
    data = np.random.default_rng(5).uniform(0.0, 2.0, (8, 8, 8)).astype(np.float32)
    data[1, 2, 3], data[4, 4, 4] = -1e-6, -3e-5
    gridio.write_vol(tmp_path / "noisy.vol", data)
    clean = np.maximum(data, 0.0)
    gridio.write_vol(tmp_path / "clean.vol", clean)
    with pytest.warns(UserWarning, match=r"density: 2 value\(s\) in \[-0.0001, 0\) "
                                         r"\(smallest -3e-05\) set to 0"):
        noisy = mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / "noisy.vol"),
                              "storage": storage})
    reference = mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / "clean.vol"),
                              "storage": storage})
    points = np.random.default_rng(6).uniform(0.0, 1.0, (500, 3))
    np.testing.assert_array_equal(medium_at(noisy, "eval_sigma_t", points),
                                  medium_at(reference, "eval_sigma_t", points))
    data[0, 0, 0] = -0.01
    gridio.write_vol(tmp_path / "negative.vol", data)
    with pytest.raises(Exception, match="density: negative value -0.01; allowed: >= 0"):
        mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / "negative.vol"),
                      "storage": storage})


def test_edits_keep_the_majorant_cells_and_refinement(grids):
    """Issue 48: after an edit (an optimiser's step) the majorant grid keeps the shape of
    cells chosen at load and hot-cell refinement, once on, stays on, so the kernels stay
    the same; the new bounds still bound. A fresh load at the edited scale chooses other
    cells (so the edit would have changed them)."""
    def load_at(scale):
        scene = _scene({"type": "grid_medium", "filename": str(grids / "gray.vol"),
                        "scale": scale})
        return scene, scene.shapes()[0].interior_medium()
    scene, medium = load_at(0.05)
    cells, refinement = medium.majorant_grid.resolution, medium.refinement
    params = mi.traverse(scene)
    params["box.interior_medium.scale"] = 500.0
    params.update()
    _, fresh = load_at(500.0)
    assert fresh.majorant_grid.resolution != cells
    assert medium.majorant_grid.resolution == cells
    assert (refinement is None) and medium.refinement is not None   # switched on once
    assert float(medium.global_majorant[0]) == pytest.approx(float(fresh.global_majorant[0]))
    params["box.interior_medium.scale"] = 0.05
    params.update()
    assert medium.majorant_grid.resolution == cells and medium.refinement is not None
