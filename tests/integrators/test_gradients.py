"""Issue 26: gradients of ``volpath_delta`` (path replay, mitsuba_plugins.tracking.replay).

Every statistical check is Welch's t-test of the derivative of an image's mean along a
parameter direction: ours (8 gradient renders, seeds 0-7) against central finite
differences of the primal render with common random numbers (Richardson-extrapolated,
8 seeds). A check fails below p = ALPHA: Sidak over the TESTS t-tests of this module
at a family-wise false-alarm rate of 1% (the media configurations of Mitsuba's AD
integrator tests, ``test_mitsuba_ad_configurations``, included). Forward against backward mode is exact (same seed,
same terms): ``<forward(v), w> = <v, backward(w)>`` to float rounding.
"""
from __future__ import annotations

import itertools

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import (SMOKE, camera, grid, load, make_vdb, media_scene,
                     software_dense_textures)
from mitsuba_plugins.tools import gradcheck

TESTS = 37   # t-tests of this module in RGB, test by test: 11 + 3 + 2 + 3 + 7 + 4 + 1 + 5 + 1
ALPHA = 1.0 - (1.0 - 0.01) ** (1.0 / TESTS)
SEEDS = range(8)
SPP_GRAD = 128
SPP_FD = 1024
H = 0.02                       # finite-difference step along a direction
DEPTH = 4

GRID = "ball.interior_medium"


def hg(medium: dict, g: float = 0.3) -> dict:
    return dict(medium, phase={"type": "hg", "g": g})


def base_scene(**medium):
    """The smoke in a ball over a floor, lit by a small light and the environment; an HG
    phase function so that ``g`` can be differentiated."""
    return media_scene(hg(grid(**medium)), sensor=camera(res=8))


def directions(params, keys, seed=0) -> dict:
    """One direction per key: a smooth field times the density grid; relative steps for
    the scalars (scale, sigma_t, emission), 0.1 for the albedo and 1 for g."""
    out = {}
    for key in keys:
        value = np.array(params[key])
        if key.endswith(".data") or key.endswith("bricks"):
            out[key] = gradcheck.smooth_direction(value.shape, seed) * value
        elif key.endswith("reflectance.value") and mi.is_spectral:
            # sigmoid-polynomial coefficients (c0 lambda^2 + c1 lambda + c2): the constant
            # term only (a step in c0 of 0.002 moves the polynomial by ~600 at 550 nm)
            out[key] = np.zeros(value.shape)
            out[key][-1] = 0.1                  # Color3f: (coefficient, lanes)
        elif key.endswith("albedo.value.value") or key.endswith("reflectance.value"):
            out[key] = np.full(value.shape, 0.1)
        elif key.endswith(".g"):
            out[key] = np.ones(value.shape)
        else:
            out[key] = value.copy()
    return out


def compare_with_finite_differences(scene, keys, integrator: dict, name: str):
    """z-test of each key's directional derivative against finite differences."""
    params = mi.traverse(scene)
    dirs = directions(params, keys)
    ours = mi.load_dict(integrator)
    grads = [gradcheck.backward_derivatives(scene, params, dirs, ours, seed, SPP_GRAD)
             for seed in SEEDS]
    primal = mi.load_dict({k: v for k, v in integrator.items() if k != "gradient_estimator"})
    failures = []
    for key in keys:
        g = [x[key] for x in grads]
        fd = [gradcheck.finite_difference(scene, params, {key: dirs[key]}, H, primal,
                                          100 + seed, SPP_FD) for seed in SEEDS]
        t, p = gradcheck.welch(g, fd)
        assert np.all(np.isfinite(g)), f"{name} {key}: non-finite gradients {g}"
        line = (f"{name} {key}: ours {np.mean(g):+.5f} +- {np.std(g, ddof=1) / 8 ** .5:.5f}"
                f", finite differences {np.mean(fd):+.5f} +- "
                f"{np.std(fd, ddof=1) / 8 ** .5:.5f}, t = {t:+.2f}, p = {p:.2g}")
        print(line)
        if not p > ALPHA:
            failures.append(line)
        # a derivative that is 0 everywhere would pass any z-test against a noisy 0
        assert abs(np.mean(fd)) > 3 * np.std(fd, ddof=1) / 8 ** .5, \
            f"{name} {key}: the finite difference is not significant; pick a direction"
    assert not failures, "\n".join(failures)


KEYS = [f"{GRID}.data", f"{GRID}.scale", f"{GRID}.albedo.value.value",
        f"{GRID}.phase_function.g", "floor.bsdf.reflectance.value"]


@pytest.mark.parametrize("estimator", ["drt", "delta", "sm"])
def test_gradients_match_finite_differences(estimator):
    """Density (a smooth direction in the grid), scale, albedo, g and the floor's
    reflectance; ``delta`` differs from ``drt`` only in the density's derivative (scale,
    albedo, g and the BSDF take the same terms), so it checks the density alone; ``sm``
    moves ``sigma_s``'s terms too (density, scale, albedo), so it checks them all."""
    compare_with_finite_differences(
        base_scene(), KEYS[:1] if estimator == "delta" else KEYS,
        {"type": "volpath_delta", "max_depth": DEPTH, "gradient_estimator": estimator},
        estimator)


def test_gradients_where_prbvolpath_fails():
    """Camera inside an emissive medium with chromatic extinction (prbvolpath: 0 inside,
    3.7x off with emission, one channel at random for RGB extinction; issue 26)."""
    desc = media_scene(hg(grid(sigma_t={"type": "rgb", "value": [1.0, 0.5, 0.25]},
                               emission={"type": "rgb", "value": [2.0, 1.0, 0.5]})),
                       sensor=camera(res=8, origin=(0.1, 0.0, 0.3)), as_dict=True)
    # one medium, inside the ball and around the camera
    desc["smoke"] = dict(desc["ball"].pop("interior"), id="smoke")
    desc["ball"]["interior"] = {"type": "ref", "id": "smoke"}
    desc["sensor"]["medium"] = {"type": "ref", "id": "smoke"}
    # the sigma_t multiplier is differentiable in RGB variants only (upsampled on the host
    # elsewhere; docs/usage.md, Gradients)
    names = ("data", "sigma_t", "emission.value.value") if mi.is_rgb else \
        ("data", "emission.value.value")
    compare_with_finite_differences(
        mi.load_dict(desc), [f"sensor.medium.{k}" for k in names],
        {"type": "volpath_delta", "max_depth": DEPTH}, "inside-emissive-chromatic")


@pytest.mark.parametrize("estimator", ["drt", "sm"])
def test_shadow_rays_carry_the_transmittance_derivative(estimator):
    """The floor in the ball's shadow, seen past the ball, with no environment and a
    low albedo: the density's derivative is mostly the direct light's transmittance
    through the ball, most of it taken on shadow rays (the small light's MIS weight)."""
    sensor = camera(res=8, origin=(-2.5, 0.0, -2.5), target=(-0.76, -1.05, -0.57), fov=15.0)
    compare_with_finite_differences(
        media_scene(grid(albedo=0.2), sensor=sensor, env=0), [f"{GRID}.data"],
        {"type": "volpath_delta", "max_depth": DEPTH, "gradient_estimator": estimator},
        f"shadow-{estimator}")


@pytest.mark.parametrize("estimator", ["drt", "sm"])
@pytest.mark.parametrize("slots", [2, 16])
def test_the_replay_gathers_what_the_primal_pass_gathered(monkeypatch, estimator, slots):
    """The replay reads the shadow rays' transmittance the primal pass stored (the
    first ``slots`` events of a path) and walks the later ones again with the same
    numbers: the radiance it rebuilds sample by sample equals the primal pass's, or
    every ``after`` it propagates would be wrong. Long paths (albedo 0.95, max_depth
    40) pass the stored events."""
    from mitsuba_plugins import differentiable
    from mitsuba_plugins.tracking import replay as replay_module
    monkeypatch.setattr(replay_module, "STORED_VERTICES", slots)
    scene = base_scene(albedo=0.95)
    integrator = mi.load_dict({"type": "volpath_delta", "max_depth": 40,
                               "gradient_estimator": estimator})
    sensor = scene.sensors()[0]
    render = differentiable.ReplayRender(integrator, sensor, 5)
    with dr.suspend_grad():
        sampler, _ = render.prepare(sensor, 5, 16, [])
        ray, _, _ = render.sample_rays(scene, sensor, sampler)
        L, _, _, state = render.sample(dr.ADMode.Primal, scene, sampler.clone(), ray)
        L_replay, _, _, _ = render.sample(dr.ADMode.Backward, scene, sampler, ray,
                                          δL=dr.zeros(mi.Spectrum, dr.width(ray)),
                                          state_in=state)
        assert render.shadows.slots == slots
        primal, replayed = np.array(L), np.array(L_replay)
    assert np.all(np.isfinite(primal)) and np.mean(primal) > 0
    np.testing.assert_allclose(replayed, primal, rtol=1e-5, atol=1e-7)


def test_the_shadow_store_stays_within_its_cap():
    """The store keeps at most max_depth and STORED_VERTICES events per lane, within
    STORE_BYTES; past that it keeps fewer, then none (every replay walks again)."""
    from mitsuba_plugins.tracking.replay import STORE_BYTES, STORED_VERTICES, ShadowStore
    per_event = 4 * dr.size_v(mi.Spectrum)
    assert ShadowStore.capacity(1000, 8) == 8
    assert ShadowStore.capacity(1000, -1) == ShadowStore.capacity(1000, 64) == STORED_VERTICES
    assert ShadowStore.capacity(1000, 0) == 0
    wide = STORE_BYTES // (per_event * 4)          # room for 4 events per lane
    assert ShadowStore.capacity(wide, -1) == 4
    assert ShadowStore.capacity(STORE_BYTES, -1) == 0
    for width in (1, 1000, wide, 10 * wide):
        assert ShadowStore.capacity(width, -1) * width * per_event <= STORE_BYTES


def test_mitsuba_media(tmp_path):
    """Mitsuba's own heterogeneous (gridvolume) and homogeneous media: their extinction
    and albedo."""
    from mitsuba_plugins.grids import gridio
    path = str(tmp_path / "g.vol")
    rng = np.random.default_rng(1)
    gridio.write_vol(path, rng.uniform(0.5, 2.0, (8, 8, 8, 1)).astype(np.float32))
    to_world = mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)
    desc = media_scene(hg({"type": "heterogeneous", "albedo": 0.8, "scale": 2.0,
                           "sigma_t": {"type": "gridvolume", "filename": path,
                                       "to_world": to_world}}),
                       sensor=camera(res=8), as_dict=True)
    desc["cube"] = {"type": "cube", "bsdf": {"type": "null"},
                    "to_world": mi.ScalarTransform4f().translate([0.3, 0.2, 1.8]).scale(0.5),
                    "interior": {"type": "homogeneous", "albedo": 0.5, "scale": 3.0,
                                 "sigma_t": {"type": "rgb", "value": [0.8, 0.8, 0.8]}}}
    scene = mi.load_dict(desc)
    compare_with_finite_differences(
        scene, [f"{GRID}.sigma_t.data", f"{GRID}.albedo.value.value",
                "cube.interior_medium.sigma_t.value.value"],
        {"type": "volpath_delta", "max_depth": DEPTH}, "mitsuba-media")


def _density_grad(storage: str, data: str):
    """d(mean image)/d(density) by backward mode with ``storage``, as a dense grid (sparse:
    read at each voxel's owning copy, SparseGrid.densify), and (sparse) the voxels that
    every lookup reading them takes from a stored brick."""
    scene = base_scene(storage=storage, filename=data)
    params = mi.traverse(scene)
    key = f"{GRID}.{'data' if storage == 'dense' else 'bricks'}"
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, integrator=mi.load_dict(
        {"type": "volpath_delta", "max_depth": DEPTH, "gradient_estimator": "drt"}),
        spp=SPP_GRAD, seed=3)
    dr.backward(dr.mean(img, axis=None))
    grad = np.array(dr.grad(params[key]))
    if storage == "dense":
        return grad[..., 0], None
    g = next(s.interior_medium() for s in scene.shapes() if s.interior_medium()).sparse
    z, y, x = g.shape[:3]
    in_stored = np.kron(g.index_host > 0, np.ones((8, 8, 8), bool))[:z, :y, :x]
    # a lookup reading voxel v is addressed by the brick of v - d, d in {0, 1}^3
    inner = np.ones_like(in_stored)
    for d in itertools.product((0, 1), repeat=3):
        inner &= np.pad(in_stored, [(k, 0) for k in d], mode="edge")[:z, :y, :x]
    return g.densify(grad)[..., 0], inner


def test_sparse_bricks_gradient_equals_dense(tmp_path, monkeypatch):
    """Sparse storage: the gradient on each voxel's owning copy equals dense storage's
    gradient of that voxel (same seed: same lookups up to float rounding) wherever every
    lookup that reads the voxel is addressed to a stored brick: on a smoke with empty
    bricks (not stored), where the difference is a lookup addressed to an empty brick (0
    in sparse storage whatever its apron holds: docs/usage.md).

    The dense texture interpolates in software here, as the bricks do: on CUDA its
    hardware interpolation (8-bit weights) changes primal tracking decisions, and the
    two gradients then differ by other paths, not by the bookkeeping this test checks
    (measured on an H100: 1.7% of the voxels beyond the tolerance).

    The in-scattering term where sigma_t = 0 (tracking/empty_scatter.py) is left out here:
    its candidates are the points where a lookup gives 0, and beside an empty brick sparse
    storage gives 0 where dense storage interpolates the stored neighbours, so the two
    keep different points (and reservoir choices) and their gradients differ by that
    term's noise; it is tested against finite differences in
    ``test_density_grows_where_the_grid_is_empty``. For the same reason the estimator is
    ``drt``: ``sm``'s reservoir weighs every point of the camera's flights by its
    ``sigma_t``, which differs there too (with the default, ``sm``, 10.9% of the voxels
    differed beyond the tolerance)."""
    from mitsuba_plugins.grids import gridio
    from mitsuba_plugins.tracking import empty_scatter
    software_dense_textures(monkeypatch)
    monkeypatch.setattr(empty_scatter, "applies", lambda media: False)
    data, _ = gridio.read_grid(SMOKE)
    data = data.copy()
    data[:, :, :16] = 0.0          # two brick columns empty: not stored
    data[40:] = 0.0
    path = str(tmp_path / "holes.vol")
    gridio.write_vol(path, data)
    dense, _ = _density_grad("dense", path)
    sparse, inner = _density_grad("sparse", path)
    assert 0.5 < inner.mean() < 0.9
    assert np.abs(dense[inner]).sum() > 0.5 * np.abs(dense).sum()
    np.testing.assert_allclose(sparse[inner], dense[inner], rtol=0,
                               atol=1e-5 * np.abs(dense).max())


@pytest.mark.parametrize("albedo,depth,estimator,hide", [
    (0.0, DEPTH, "drt", False), (0.85, 2, "drt", False), (0.85, DEPTH, "drt", False),
    (0.85, 2, "sm", False), (0.85, DEPTH, "sm", False), (0.85, 2, "drt", True),
    (0.85, 2, "sm", True)])
def test_density_grows_where_the_grid_is_empty(tmp_path, albedo, depth, estimator, hide):
    """A direction that adds density only where the grid is 0 (over whole majorant cells:
    delta tracking samples no point there; the drt rules still do, shadow rays at a floor
    rate): ours against one-sided finite differences. Absorbing (albedo 0): the
    attenuation a new density would cause. Scattering: also the light it would scatter,
    which no real collision estimates where sigma_t = 0
    (:mod:`mitsuba_plugins.tracking.empty_scatter`; before it, at max_depth 2: -0.167
    against finite differences' -0.081, t = -23.9). ``sm`` takes both terms at its
    matched points, which include these. ``hide``: emitters hidden, so a ray through
    the empty slabs to the environment sees nothing, yet a new density there would
    scatter light toward it (such lanes were once left out of the sub-path's term:
    ``sm`` gave -0.0044 against finite differences' +0.0005 on a uniform grid)."""
    from mitsuba_plugins.grids import gridio
    data, _ = gridio.read_grid(SMOKE)
    data = data.copy()
    data[:, :, :16] = 0.0
    data[40:] = 0.0
    path = str(tmp_path / "holes.vol")
    gridio.write_vol(path, data)
    scene = base_scene(filename=path, albedo=albedo)
    params = mi.traverse(scene)
    key = f"{GRID}.data"
    empty = (data == 0).astype(np.float64)
    hidden = {"hide_emitters": True} if hide else {}
    direction = {key: gradcheck.smooth_direction(data.shape, 5) * empty * 0.5}
    ours = mi.load_dict({"type": "volpath_delta", "max_depth": depth,
                         "gradient_estimator": estimator, **hidden})
    g = [gradcheck.backward_derivatives(scene, params, direction, ours, seed, SPP_GRAD)[key]
         for seed in SEEDS]
    primal = mi.load_dict({"type": "volpath_delta", "max_depth": depth, **hidden})
    # hidden emitters: the derivative is the light new density scatters in, curbed at
    # second order by its own attenuation, so the one-sided difference's truncation
    # shows at H (0.0214 +- 0.0020 at H, 0.0275 +- 0.0038 at H / 4, ours 0.028)
    h = H / 4 if hide else H
    fd = [gradcheck.finite_difference(scene, params, direction, h, primal, 100 + seed, SPP_FD,
                                      one_sided=True)     # density >= 0
          for seed in SEEDS]
    t, p = gradcheck.welch(g, fd)
    print(f"empty cells, {estimator}, albedo {albedo}, max_depth {depth}, hide {hide}: ours {np.mean(g):+.5f}, finite differences {np.mean(fd):+.5f}, "
          f"t = {t:+.2f}, p = {p:.2g}")
    assert abs(np.mean(fd)) > 3 * np.std(fd, ddof=1) / 8 ** .5
    assert p > ALPHA, (np.mean(g), np.mean(fd), t, p)


def test_sparse_and_emission_grids_and_albedo_grid(tmp_path):
    """A .vdb with a density, a 'temperature' emission grid and a 'tint' albedo_grid
    stored sparse, and an albedo gridvolume: the stored bricks of the three grids and the
    gridvolume's data, against finite differences."""
    from mitsuba_plugins.grids import gridio
    n = 16
    z, y, x = np.meshgrid(*(np.linspace(-1, 1, n),) * 3, indexing="ij")
    r2 = x * x + y * y + z * z
    density = np.where(r2 < 0.8, 2.0 * np.exp(-2.0 * r2), 0.0).astype(np.float32)
    temperature = np.where(r2 < 0.3, 3.0 * (0.3 - r2) / 0.3, 0.0).astype(np.float32)
    tint = np.where(r2 < 0.9, 0.7 + 0.3 * np.exp(-3.0 * r2), 0.0).astype(np.float32)
    make_vdb(tmp_path / "fire.vdb", """
        for name, values in (("density", density), ("temperature", temperature),
                             ("tint", tint)):
            g = vdb.FloatGrid(); g.name = name
            g.copyFromArray(values); g.transform = vdb.createLinearTransform(1.0 / 16)
            grids.append(g)
    """, density=density, temperature=temperature, tint=tint)
    rng = np.random.default_rng(2)
    gridio.write_vol(str(tmp_path / "albedo.vol"),
                     rng.uniform(0.5, 0.95, (4, 4, 4, 1)).astype(np.float32))
    medium = grid(filename=str(tmp_path / "fire.vdb"), storage="sparse",
                  emission_grid="temperature",
                  emission={"type": "rgb", "value": [2.0, 1.0, 0.5]},
                  albedo={"type": "gridvolume", "filename": str(tmp_path / "albedo.vol")},
                  albedo_grid="tint")
    scene = media_scene(hg(medium), sensor=camera(res=8))
    compare_with_finite_differences(
        scene, [f"{GRID}.bricks", f"{GRID}.emission_bricks", f"{GRID}.albedo.data",
                f"{GRID}.albedo_bricks"],
        {"type": "volpath_delta", "max_depth": DEPTH}, "sparse-emission-albedo")


def test_sample_matching_on_sparse_storage(tmp_path):
    """``sm`` (the default on this gray grid) on a grid stored as sparse bricks, with
    empty bricks beside stored ones: the bricks' derivative against finite differences
    (the bookkeeping test above compares with dense storage under ``drt`` only)."""
    from mitsuba_plugins.grids import gridio
    data, _ = gridio.read_grid(SMOKE)
    data = data.copy()
    data[:, :, :16] = 0.0
    path = str(tmp_path / "holes.vol")
    gridio.write_vol(path, data)
    compare_with_finite_differences(
        base_scene(storage="sparse", filename=path), [f"{GRID}.bricks"],
        {"type": "volpath_delta", "max_depth": DEPTH, "gradient_estimator": "sm"},
        "sm-sparse")


@pytest.mark.parametrize("estimator", ["drt", "sm"])
def test_forward_equals_backward(estimator):
    """<forward(v), w> = <v, backward(w)>: the same replay read both ways, exact up to
    float rounding (same seed)."""
    scene = base_scene()
    params = mi.traverse(scene)
    # every kind: density, scale, albedo, HG g and the floor's BSDF
    dirs = directions(params, KEYS, seed=3)
    w = np.random.default_rng(4).uniform(0.0, 1.0, (8, 8, 3))
    integrator = mi.load_dict({"type": "volpath_delta", "max_depth": DEPTH,
                               "gradient_estimator": estimator})
    fwd = gradcheck.forward_image(scene, params, dirs, integrator, seed=5, spp=SPP_GRAD)
    bwd = gradcheck.backward_derivatives(scene, params, dirs, integrator, seed=5,
                                         spp=SPP_GRAD, weights=w)
    lhs, rhs = float(np.mean(fwd * w)), sum(bwd.values())
    assert abs(lhs) > 1e-4
    assert lhs == pytest.approx(rhs, rel=1e-4), (lhs, bwd)


# -- Mitsuba's AD integrator tests' media configurations (issue 46) --------------------
CUBE = "cube.interior_medium"


def _cube_scene(medium: dict, light: str) -> mi.Scene:
    """A cube of ``medium`` behind a null boundary, under a constant environment
    (``light = "constant"``) or lit by a rectangular area light behind it, facing the
    camera (``"rect"``), as the volume configurations of Mitsuba's
    ``test_ad_integrators.py`` (pull request #678) set them up."""
    desc = {"type": "scene", "sensor": camera(res=8, origin=(0.0, 0.0, 4.0), fov=40.0),
            "cube": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium,
                     "to_world": mi.ScalarTransform4f().scale(0.8)}}
    if light == "constant":
        desc["env"] = {"type": "constant"}
    else:
        desc["rect"] = {"type": "rectangle", "emitter": {"type": "area", "radiance": 4.0},
                        "to_world": mi.ScalarTransform4f().translate([0.0, 0.0, -2.0])}
    return mi.load_dict(desc)


def _homogeneous(**kw) -> dict:
    """As Mitsuba's tests: RGB values in RGB variants; elsewhere uniform spectra (an RGB
    value there is a sigmoid polynomial's coefficients, which ``+ theta`` does not
    perturb as a value)."""
    if mi.is_rgb:
        albedo, sigma_t = ({"type": "rgb", "value": [v] * 3} for v in (0.5, 1.0))
    else:
        albedo, sigma_t = 0.5, 1.0
    return dict({"type": "homogeneous", "albedo": albedo, "sigma_t": sigma_t, "scale": 0.8,
                 "phase": {"type": "hg", "g": 0.3}}, **kw)


def _heterogeneous(tmp_path) -> dict:
    from mitsuba_plugins.grids import gridio
    path = str(tmp_path / "h.vol")
    rng = np.random.default_rng(2)
    gridio.write_vol(path, rng.uniform(0.2, 1.5, (6, 6, 6, 1)).astype(np.float32))
    return {"type": "heterogeneous", "albedo": 0.6, "phase": {"type": "hg", "g": 0.3},
            "sigma_t": {"type": "gridvolume", "filename": path,
                        "to_world": mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)}}


#: (name, light, medium kind, parameter, max_depth): the configurations of that file
#: that stock Mitsuba loads
MITSUBA_AD_CONFIGS = [
    ("MediumConstantEmitterSigmaT", "constant", "homogeneous", "sigma_t.value.value", 2),
    ("MediumConstantEmitterAlbedo", "constant", "homogeneous", "albedo.value.value", 2),
    ("AreaLightIllumRectMediumSigmaT", "rect", "homogeneous", "sigma_t.value.value", 3),
    ("AreaLightIllumRectMediumAlbedo", "rect", "homogeneous", "albedo.value.value", 3),
    ("HeterogeneousMediumSigmaT", "constant", "heterogeneous", "sigma_t.data", 3),
]


@pytest.mark.parametrize("name,light,kind,param,depth", MITSUBA_AD_CONFIGS,
                         ids=[c[0] for c in MITSUBA_AD_CONFIGS])
def test_mitsuba_ad_configurations(tmp_path, name, light, kind, param, depth):
    """Forward and backward mode as Mitsuba's tests write them (``params[key] = value +
    theta``): equal to float rounding, and both agree with central finite differences
    (Welch's t-test, 8 seeds each). Forward mode gave -0.0757 where finite differences
    give -0.1823 on the first configuration before issue 46's fix (a homogeneous
    medium's sigma_s and sigma_t evaluated together: the second lost its tangent)."""
    medium = _homogeneous() if kind == "homogeneous" else _heterogeneous(tmp_path)
    scene = _cube_scene(medium, light)
    params = mi.traverse(scene)
    key = f"{CUBE}.{param}"
    desc = {"type": "volpath_delta", "max_depth": depth}
    integrator = mi.load_dict(desc)
    fwd, bwd = zip(*(gradcheck.theta_derivatives(scene, params, key, integrator, seed,
                                                 SPP_GRAD // 2) for seed in SEEDS))
    np.testing.assert_allclose(fwd, bwd, rtol=1e-4, atol=1e-7)
    ones = np.ones(np.array(params[key]).shape)
    fd = [gradcheck.finite_difference(scene, params, {key: ones}, H, mi.load_dict(desc),
                                      100 + seed, SPP_FD // 2) for seed in SEEDS]
    t, p = gradcheck.welch(fwd, fd)
    print(f"{name}: forward {np.mean(fwd):+.5f}, finite differences {np.mean(fd):+.5f}, "
          f"t = {t:+.2f}, p = {p:.2g}")
    assert abs(np.mean(fd)) > 3 * np.std(fd, ddof=1) / 8 ** .5
    assert p > ALPHA, (name, np.mean(fwd), np.mean(fd), t, p)


def _media_kinds(tmp_path) -> dict:
    """``{kind: (scene, [differentiable parameters])}``: every medium kind our replay
    differentiates, with every parameter it exposes as differentiable."""
    grid_keys = ["data", "scale", "albedo.value.value", "phase_function.g",
                 "emission.value.value"] + (["sigma_t"] if mi.is_rgb else [])
    return {
        "homogeneous": (_cube_scene(_homogeneous(), "rect"),
                        ["sigma_t.value.value", "albedo.value.value", "phase_function.g"]),
        "heterogeneous": (_cube_scene(_heterogeneous(tmp_path), "rect"),
                          ["sigma_t.data", "albedo.value.value", "phase_function.g"]),
        "grid_medium": (_cube_scene(hg(grid(emission={"type": "rgb", "value": 0.5})), "rect"),
                        grid_keys),
    }


@pytest.mark.parametrize("kind", ["homogeneous", "heterogeneous", "grid_medium"])
def test_forward_equals_backward_every_medium(tmp_path, kind):
    """``<forward(v), w> = <v, backward(w)>`` (rel. 1e-4) for every differentiable
    parameter of every medium kind, each alone along ``theta`` as Mitsuba's tests
    perturb it; each derivative non-zero."""
    scene, names = _media_kinds(tmp_path)[kind]
    params = mi.traverse(scene)
    integrator = mi.load_dict({"type": "volpath_delta", "max_depth": 4})
    for name in names:
        fwd, bwd = gradcheck.theta_derivatives(scene, params, f"{CUBE}.{name}", integrator,
                                               seed=3, spp=32)
        assert abs(bwd) > 1e-6, (kind, name, fwd, bwd)
        assert fwd == pytest.approx(bwd, rel=1e-4), (kind, name, fwd, bwd)


@pytest.mark.skipif(not mi.is_rgb, reason="grid_medium's sigma_t is differentiable in RGB "
                    "variants only (upsampled on the host elsewhere)")
def test_gray_sigma_t_gradient_lands_on_its_channel():
    """A gray ``sigma_t`` multiplier (the default) gets the derivative of channel c's
    mean on channel c alone, in both modes (before issue 46's fix, G's derivative landed
    on R: ``[-0.0112, 0, 0]``; the folded gray scalar carried channel R's only). The
    scene is gray, so the three derivatives are equal."""
    scene = _cube_scene(grid(), "rect")
    params = mi.traverse(scene)
    key = f"{CUBE}.sigma_t"
    integrator = mi.load_dict({"type": "volpath_delta", "max_depth": 4})
    grads = []
    for channel in range(3):
        dr.enable_grad(params[key])
        params.update()
        img = mi.render(scene, params, integrator=integrator, spp=32, seed=0)
        dr.backward(dr.mean(img[..., channel], axis=None))
        grads.append(np.array(dr.grad(params[key])).ravel())
        params[key] = mi.Color3f(1.0)
        params.update()
    grads = np.array(grads)
    assert grads[0, 0] < -1e-3, grads
    np.testing.assert_allclose(grads, np.eye(3) * grads[0, 0], rtol=1e-4, atol=1e-7)
    # forward mode along G alone
    v = np.zeros((3, 1))
    v[1] = 1.0
    fwd = gradcheck.forward_image(scene, params, {key: v}, integrator, seed=0, spp=32)
    assert np.mean(fwd[..., 1]) < -1e-4, np.mean(fwd[..., 1])


def test_against_prbvolpath():
    """Gray medium, camera outside, no emission (where prbvolpath is right): the density
    derivative of both agree (Welch z-test, 8 renders each)."""
    scene = base_scene()
    params = mi.traverse(scene)
    dirs = directions(params, [f"{GRID}.data"])
    ours, theirs = ({"type": "volpath_delta", "max_depth": DEPTH},
                    {"type": "prbvolpath", "max_depth": DEPTH})
    values = {}
    for name, desc in (("ours", ours), ("prbvolpath", theirs)):
        integrator = mi.load_dict(desc)
        values[name] = [gradcheck.backward_derivatives(scene, params, dirs, integrator, seed,
                                                       SPP_GRAD)[f"{GRID}.data"]
                        for seed in SEEDS]
    t, p = gradcheck.welch(values["ours"], values["prbvolpath"])
    assert p > ALPHA, (np.mean(values["ours"]), np.mean(values["prbvolpath"]), t, p)


@pytest.mark.parametrize("case", ["dense", "albedo_0.999", "empty", "one_voxel"])
def test_hard_cases_give_finite_gradients(case):
    """Optical depth 50+ across the ball, albedo 0.999, an empty grid and a grid with one
    non-zero voxel: every gradient finite, no NaN/Inf sample in the primal pass."""
    scene = base_scene(scale=80.0 if case == "dense" else 8.0,
                       albedo=0.999 if case == "albedo_0.999" else 0.85)
    params = mi.traverse(scene)
    key = f"{GRID}.data"
    data = np.array(params[key])
    if case in ("empty", "one_voxel"):
        data = np.zeros_like(data)
        if case == "one_voxel":
            data[tuple(s // 2 for s in data.shape[:3])] = 50.0
        params[key] = mi.TensorXf(data)
        params.update()
    integrator = mi.load_dict({"type": "volpath_delta", "max_depth": 16})
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, integrator=integrator, spp=32, seed=0)
    dr.backward(dr.mean(img, axis=None))
    grad = np.array(dr.grad(params[key]))
    assert np.all(np.isfinite(grad)), f"{case}: {np.sum(~np.isfinite(grad))} non-finite"
    assert integrator.sample_guard.take() == 0, f"{case}: NaN/Inf samples in the primal pass"
    if case != "empty":
        assert np.abs(grad).sum() > 0


# -- what stays refused ----------------------------------------------------------------
REFUSED = {"direct_mis": "prb", "path_rr": "prb", "volpath_raymarch": "prbvolpath"}


def _scene_and_key(name):
    if name.startswith("volpath"):
        scene = media_scene(grid(), sensor=camera(res=8))
        suffix = ".albedo.value.value"
    else:
        scene = load("cornell_box", res=8)
        suffix = ".reflectance.value"
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith(suffix))
    return scene, params, key


def _messages(error: BaseException) -> str:
    text = []
    while error is not None:
        text.append(str(error))
        error = error.__cause__ or error.__context__
    return " | ".join(text)


def _differentiate(scene, params, key, integrator, mode):
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, integrator=integrator, spp=4)
    if mode == "backward":
        dr.backward(dr.mean(img, axis=None))
    else:
        dr.forward(params[key])
        dr.grad(img)


@pytest.mark.parametrize("mode", ["backward", "forward"])
@pytest.mark.parametrize("name", list(REFUSED))
def test_differentiating_other_integrators_is_refused(name, mode):
    """Their gradients would be silently wrong (measured before issue 26: d(mean)/d(density)
    -1.1e-4 with volpath_raymarch where prbvolpath gives +5.4e-4)."""
    scene, params, key = _scene_and_key(name)
    integrator = mi.load_dict({"type": name} if name == "direct_mis" else
                              {"type": name, "max_depth": 4})
    with pytest.raises(Exception) as info:
        _differentiate(scene, params, key, integrator, mode)
    assert (f"{name}: differentiable rendering is not supported (its gradients would be "
            f"wrong); render the gradient with Mitsuba's '{REFUSED[name]}' integrator"
            in _messages(info.value))


#: settings of volpath_delta whose gradients are not implemented, and what the refusal says
UNDIFFERENTIATED = {
    "decomposition": ({"free_flight": "decomposition"}, "gradients need free_flight = 'delta'"),
    "equiangular": ({"equiangular": True}, "gradients need equiangular = false"),
    "guiding": ({"guiding": "volumes"}, "gradients need guiding = 'off'"),
}


@pytest.mark.parametrize("setting", list(UNDIFFERENTIATED))
def test_settings_without_gradients_are_refused(setting):
    extra, message = UNDIFFERENTIATED[setting]
    scene, params, key = _scene_and_key("volpath_delta")
    integrator = mi.load_dict({"type": "volpath_delta", **extra})
    with pytest.raises(Exception) as info:
        _differentiate(scene, params, key, integrator, "backward")
    assert f"volpath_delta: {message}" in _messages(info.value)


def test_sample_matching_refuses_emitting_media():
    """``sm`` keeps the light a path gathers after a flight's start, emission on the
    flight included: refused in one line naming the allowed estimators."""
    scene = media_scene(grid(emission={"type": "rgb", "value": [1.0, 0.5, 0.2]}),
                        sensor=camera(res=8))
    params = mi.traverse(scene)
    key = f"{GRID}.data"
    integrator = mi.load_dict({"type": "volpath_delta", "gradient_estimator": "sm"})
    with pytest.raises(Exception) as info:
        _differentiate(scene, params, key, integrator, "backward")
    assert "gradient_estimator='sm' needs gray, non-emitting" in _messages(info.value)


@pytest.mark.parametrize("emitting", [False, True])
def test_default_estimator_is_sample_matching_where_it_applies(emitting):
    """The default ``gradient_estimator = "auto"``: on a gray grid the gradient of
    ``sm``, on an emitting grid, where ``sm`` is refused,
    that of ``drt`` (to float rounding); and the two differ, so the comparison tells them
    apart."""
    medium = grid(emission={"type": "rgb", "value": [1.0, 0.5, 0.2]}) if emitting else grid()
    scene = media_scene(medium, sensor=camera(res=8))
    params = mi.traverse(scene)
    key = f"{GRID}.data"
    dirs = directions(params, [key])
    got = {}
    for name in ("auto", "drt", "sm"):
        if emitting and name == "sm":
            continue
        extra = {} if name == "auto" else {"gradient_estimator": name}
        integrator = mi.load_dict({"type": "volpath_delta", "max_depth": DEPTH, **extra})
        got[name] = gradcheck.backward_derivatives(scene, params, dirs, integrator, 0, 16)[key]
    # the same kernel; backward's atomic additions run in any order: float rounding
    assert np.isfinite(got["auto"])
    assert got["auto"] == pytest.approx(got["drt" if emitting else "sm"], rel=1e-6), got
    if not emitting:
        assert abs(got["sm"] - got["drt"]) > 1e-3 * abs(got["drt"]), got


@pytest.mark.parametrize("flags, expected", [
    (dict(heterogeneous=True, chromatic_heterogeneous=False, emission=False), "sm"),
    (dict(heterogeneous=True, chromatic_heterogeneous=True, emission=False), "drt"),
    (dict(heterogeneous=True, chromatic_heterogeneous=False, emission=True), "drt"),
    (dict(heterogeneous=False, chromatic_heterogeneous=False, emission=False), "drt")])
def test_auto_resolves_by_the_scene_media(flags, expected):
    """``auto`` is ``sm`` only for gray, non-emitting heterogeneous media; explicit names
    are kept as given (``sm`` is then checked, and refused, by the replay)."""
    from types import SimpleNamespace
    from mitsuba_plugins.tracking.empty_scatter import resolve
    media = SimpleNamespace(**flags)
    assert resolve("auto", media) == expected
    assert [resolve(name, media) for name in ("drt", "delta", "sm")] == ["drt", "delta", "sm"]


@pytest.mark.parametrize("channels", [1, 3])
def test_sample_matching_on_mitsubas_heterogeneous_medium(tmp_path, channels):
    """Mitsuba's ``heterogeneous`` medium declares spectral extinction. With a
    one-channel ``sigma_t`` grid its extinction is gray all the same (Mitsuba broadcasts
    the channel; ``trackers.gray_extinction``), so ``auto`` is ``sm`` in every variant and
    the gradient is finite (its agreement with finite differences: ``test_mitsuba_media``,
    ``test_mitsuba_ad_configurations``). With three channels, where a spectrum has
    several, our tracker treats it as chromatic: ``auto`` is ``drt`` and ``sm`` is
    refused in one line."""
    from mitsuba_plugins.grids import gridio
    from mitsuba_plugins.tracking.empty_scatter import resolve
    from mitsuba_plugins.tracking.scene_media import SceneMedia
    path = str(tmp_path / "g.vol")
    values = np.full((8, 8, 8, channels), 1.5, np.float32)
    values[..., -1] *= 0.5          # chromatic where there are several channels
    gridio.write_vol(path, values)
    to_world = mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)
    scene = media_scene({"type": "heterogeneous", "albedo": 0.8, "scale": 2.0,
                         "sigma_t": {"type": "gridvolume", "filename": path,
                                     "to_world": to_world}}, sensor=camera(res=8))
    params = mi.traverse(scene)
    key = f"{GRID}.sigma_t.data"
    integrator = mi.load_dict({"type": "volpath_delta", "gradient_estimator": "sm"})
    if channels > 1 and dr.size_v(mi.Spectrum) > 1:
        assert resolve("auto", SceneMedia(scene)) == "drt"
        with pytest.raises(Exception) as info:
            _differentiate(scene, params, key, integrator, "backward")
        assert "gradient_estimator='sm' needs gray, non-emitting" in _messages(info.value)
    else:
        assert resolve("auto", SceneMedia(scene)) == "sm"
        _differentiate(scene, params, key, integrator, "backward")
        grad = np.array(dr.grad(params[key]))
        assert np.all(np.isfinite(grad)) and np.any(grad != 0)


@pytest.mark.parametrize("key", ["light.emitter.radiance.value", "env.radiance.value"])
def test_gradients_we_do_not_compute_are_refused(key):
    """Emitters: refused in one line naming the parameter, not 0. (Shapes' transforms go
    through the same check; a test that makes one differentiable, e.g. floor.to_world,
    makes a later prbvolpath render in the same process abort inside Dr.Jit, so none is
    here.)"""
    scene, params, _ = _scene_and_key("volpath_delta")
    integrator = mi.load_dict({"type": "volpath_delta", "max_depth": 4})
    with pytest.raises(Exception) as info:
        _differentiate(scene, params, key, integrator, "backward")
    assert "volpath_delta: gradients with respect to" in _messages(info.value)
    assert key.split(".", 1)[1] in _messages(info.value)


def test_primal_render_with_grad_enabled_parameters_still_works():
    scene, params, key = _scene_and_key("volpath_delta")
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, integrator=mi.load_dict({"type": "volpath_delta"}), spp=4)
    assert np.all(np.isfinite(np.array(img))) and np.array(img).mean() > 0


def test_prbvolpath_gradient_equals_heterogeneous(tmp_path):
    """d(mean image)/d(density grid) with Mitsuba's prbvolpath: grid_medium (dense storage,
    'data' exposed as differentiable) gives what heterogeneous + gridvolume gives."""
    from mitsuba_plugins.grids import gridio
    rng = np.random.default_rng(1)
    gridio.write_vol(tmp_path / "g.vol", rng.uniform(0.5, 2.0, (8, 8, 8, 1)).astype(np.float32))
    to_world = mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)
    media = {
        "grid_medium": {"type": "grid_medium", "filename": str(tmp_path / "g.vol"),
                        "albedo": 0.8, "to_world": to_world},
        "heterogeneous": {"type": "heterogeneous", "albedo": 0.8, "sigma_t": {
            "type": "gridvolume", "filename": str(tmp_path / "g.vol"), "to_world": to_world}}}
    grads = {}
    for kind, medium in media.items():
        scene = mi.load_dict({
            "type": "scene", "env": {"type": "constant"},
            "box": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium},
            "sensor": camera(res=16)})
        params = mi.traverse(scene)
        key = next(k for k in params.keys() if k.endswith("data"))
        dr.enable_grad(params[key])
        params.update()
        img = mi.render(scene, params, integrator=mi.load_dict({"type": "prbvolpath",
                                                                "max_depth": 8}),
                        spp=64, seed=1)
        dr.backward(dr.mean(img, axis=None))
        grads[kind] = np.array(dr.grad(params[key])).ravel()
    a, b = grads["grid_medium"], grads["heterogeneous"]
    assert abs(b.sum()) > 1e-3
    np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-4 * np.abs(b).max())


@pytest.mark.parametrize("estimator", ["drt", "delta", "sm"])
def test_optimisation_steps_compile_no_kernels(estimator):
    """Issue 48: ten Adam steps on the density grid and ``scale`` (two views in turn, a new
    seed per render, ``params.update()`` refitting the majorants each time) compile no
    kernel after two warm-up steps: every value that changes between steps is opaque, so
    each step launches the kernels the first ones compiled. Kernels are counted by Dr.Jit's
    kernel history (``cache_hit`` False: compiled, not taken from the cache), per step:
    at most one step may compile any (a one-off seen in whole-suite runs); a literal
    replay seed compiles in all ten."""
    scene = base_scene()
    params = mi.traverse(scene)
    keys = [f"{GRID}.data", f"{GRID}.scale"]
    sensors = [camera(res=8, origin=(0, 0, 4)), camera(res=8, origin=(4, 0, 0))]
    sensors = [mi.load_dict(s) for s in sensors]
    integrator = mi.load_dict({"type": "volpath_delta", "max_depth": 4,
                               "gradient_estimator": estimator})
    references = [mi.render(scene, sensor=s, integrator=integrator, spp=16, seed=99)
                  for s in sensors]
    for key in keys:                                  # start away from the truth
        params[key] = params[key] * 0.7
    params.update()
    opt = mi.ad.Adam(lr=0.05)
    for key in keys:
        opt[key] = params[key]
    params.update(opt)

    def step(it):
        for v, sensor in enumerate(sensors):
            img = mi.render(scene, params, sensor=sensor, integrator=integrator, spp=4,
                            seed=it * len(sensors) + v)
            dr.backward(dr.mean(dr.square(img - references[v]), axis=None))
        opt.step()
        for key in keys:
            opt[key] = dr.maximum(opt[key], 0.0)
        params.update(opt)
        dr.eval(*(params[key] for key in keys))
    start = [np.array(params[key]) for key in keys]
    for it in range(2):
        step(it)
    compiled = []                                   # per step: kernels compiled
    for it in range(2, 12):
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory):
            step(it)
            history = dr.kernel_history([dr.KernelType.JIT])
        assert len(history) > 0
        compiled.append([(h["operation_count"], h["size"]) for h in history
                         if not h["cache_hit"]])
    for key, before in zip(keys, start):                   # both did change
        assert not np.array_equal(np.array(params[key]), before), key
    # none, or (seen in whole-suite runs only, not understood: 2 of 4 on 2026-11-26 in one
    # step; once on 2026-11-27 5 kernels in one step and 1 in the next) one burst of a few
    # kernels within two consecutive steps; a value baked into a kernel compiles some in
    # every step
    steps = [i for i, c in enumerate(compiled) if c]
    assert not steps or steps[-1] - steps[0] <= 1, \
        f"kernels compiled per step 3-12 (operations, size): {compiled}"


def test_several_views_one_backward_equals_one_backward_per_view():
    """Issue 48: a step over several sensors written as one loss (the sum of every view's)
    and one ``dr.backward`` gives the gradient of one backward per view, the same seeds
    (atomic-add order aside: rtol 1e-5), and is not 0 (docs/examples/fit_grid_views.py)."""
    scene = base_scene()
    params = mi.traverse(scene)
    key = f"{GRID}.data"
    sensors = [mi.load_dict(camera(res=8, origin=o)) for o in ((0, 0, 4), (4, 0, 0))]
    integrator = mi.load_dict({"type": "volpath_delta", "max_depth": 4})
    references = [mi.render(scene, sensor=s, integrator=integrator, spp=16, seed=99) * 0.8
                  for s in sensors]

    def renders():
        for v, sensor in enumerate(sensors):
            img = mi.render(scene, params, sensor=sensor, integrator=integrator, spp=8,
                            seed=v)
            yield dr.mean(dr.square(img - references[v]), axis=None)
    grads = []
    for together in (True, False):
        dr.enable_grad(params[key])
        params.update()
        if together:
            loss = 0.0
            for view_loss in renders():
                loss += view_loss
            dr.backward(loss)
        else:
            for view_loss in renders():
                dr.backward(view_loss)
        grads.append(np.array(dr.grad(params[key])))
        dr.disable_grad(params[key])
        params.update()
    assert np.abs(grads[1]).max() > 0
    np.testing.assert_allclose(grads[0], grads[1], rtol=1e-5,
                               atol=1e-6 * np.abs(grads[1]).max())
