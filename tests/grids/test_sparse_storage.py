"""Sparse brick storage (issue 13, part 2): the builder, lookups equal to the dense
texture's (both interpolations, across brick borders, outside the box), majorants that
bound every lookup, the storage choice, degenerate grids, and renders equal to dense."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import (LUMINANCE, SMOKE, SPARSE, assert_same_expectation, assert_same_render,
                     camera, check_segment_bounds, estimate, grid, media_scene, medium_at,
                     render, software_dense_textures)
from mitsuba_plugins.grids import bricks, gridio, stores


def _random_grid(shape, fraction, rng):
    data = np.zeros(shape, np.float32)
    mask = rng.random(shape[:3]) < fraction
    data[mask] = rng.uniform(0.1, 5.0, (int(mask.sum()), shape[3]))
    return data


@pytest.mark.parametrize("shape", [(20, 13, 17, 1), (16, 16, 16, 3), (9, 8, 30, 1), (1, 5, 3, 1)])
def test_builder_round_trip_any_slab_thickness(shape):
    rng = np.random.default_rng(sum(shape))
    data = _random_grid(shape, 0.01, rng)
    builder = bricks.BrickBuilder(shape)
    z0 = 0
    while z0 < shape[0]:
        k = int(rng.integers(1, 12))
        builder.add(z0, data[z0:z0 + k])
        z0 = min(z0 + k, shape[0])
    index, pool, maxima, minima = builder.finish()
    assert np.array_equal(bricks.densify(index, pool, shape), data)
    # a stored block's extrema are those of its voxels; an empty brick's entry is slot 0
    assert np.all(maxima[index] >= 0) and not np.any(pool[0])
    for slot in range(1, builder.stored):
        assert np.array_equal(maxima[slot], pool[slot].max(axis=(0, 1, 2)))


def test_builder_refuses_out_of_order_and_short_input():
    builder = bricks.BrickBuilder((16, 4, 4, 1))
    with pytest.raises(ValueError, match="expected 0"):
        builder.add(3, np.zeros((2, 4, 4, 1), np.float32))
    builder.add(0, np.zeros((10, 4, 4, 1), np.float32))
    with pytest.raises(ValueError, match="10 of 16 z-slices"):
        builder.finish()


def test_only_bricks_a_lookup_needs_are_stored():
    """A voxel on a brick's low face makes the brick below store it as apron too."""
    data = np.zeros((32, 32, 32, 1), np.float32)
    data[8, 20, 3] = 1.0                    # brick (1, 2, 0); apron of brick (0, 2, 0)
    builder = bricks.BrickBuilder(data.shape)
    builder.add(0, data)
    index, pool, _, _ = builder.finish()
    assert sorted(zip(*np.nonzero(index))) == [(0, 2, 0), (1, 2, 0)]
    assert pool[index[0, 2, 0]][8, 4, 3, 0] == 1.0


def _pair(tmp_path, data, **kw):
    path = tmp_path / "g.vol"
    gridio.write_vol(path, data)
    to_world = mi.ScalarTransform4f().rotate([0.3, 1, 0.2], 25).scale([2.0, 1.0, 1.5])
    return [mi.load_dict({"type": "grid_medium", "filename": str(path), "storage": s,
                          "to_world": to_world, **kw}) for s in ("dense", "sparse")], to_world


def _points(rng, to_world, n, shape):
    """Random local points in [-0.1, 1.1]^3 (clamping beyond the box), half of them on
    brick faces (local coordinate = a multiple of 8 voxels, exactly where blocks meet),
    in world space."""
    local = rng.uniform(-0.1, 1.1, (n, 3))
    z, y, x = shape[:3]
    size = np.array([x, y, z], np.float64)
    faces = rng.integers(0, 3, n // 2)
    bricks_on_axis = np.ceil(size / bricks.BRICK)[faces]
    local[np.arange(n // 2), faces] = (rng.integers(0, bricks_on_axis) * bricks.BRICK
                                       / size[faces])
    m = np.array(to_world.matrix, np.float64)
    return (local @ m[:3, :3].T + m[:3, 3]).astype(np.float32)


def sigma_t_at(medium, points) -> np.ndarray:
    return medium_at(medium, "eval_sigma_t", points)


@pytest.mark.parametrize("interpolation", ["trilinear", "nearest"])
@pytest.mark.parametrize("channels", [1, 3])
def test_sparse_lookups_equal_dense(tmp_path, interpolation, channels):
    """At 20000 points (10000 on brick faces), beyond the box too: the same values up to
    float rounding of the interpolation weights (nearest: exactly)."""
    rng = np.random.default_rng(channels)
    data = _random_grid((27, 21, 34, channels), 0.03, rng)
    (dense, sparse), to_world = _pair(tmp_path, data, interpolation=interpolation,
                                      sigma_t=[1.0, 0.5, 0.25])
    assert dense.sparse is None and sparse.sparse is not None
    p = _points(rng, to_world, 20000, data.shape)
    a, b = sigma_t_at(dense, p), sigma_t_at(sparse, p)
    # the exact lookup: a software texture (CUDA's dense texture interpolates in hardware
    # with 8-bit fractional weights: measured 0.5% of the maximum away on an H100)
    exact = mi.Texture3f(mi.TensorXf(data), use_accel=False, wrap_mode=dr.WrapMode.Clamp,
                         filter_mode=(dr.FilterMode.Linear if interpolation == "trilinear"
                                      else dr.FilterMode.Nearest))
    local = mi.Transform4f(sparse.to_local) @ mi.Point3f(*(mi.Float(p[:, i]) for i in range(3)))
    value = np.array(exact.eval(local))
    factor = np.array([1.0, 0.5, 0.25])
    ref = (value if channels == 3 else np.repeat(value, 3, axis=0)) * factor[:, None]
    if mi.is_monochromatic:     # the luminance of the grid and of the factor
        ref = (LUMINANCE @ value if channels == 3 else value[0]) * (LUMINANCE @ factor)
        ref = ref[None]
    # spectral variants: the upsampled values, checked against gridvolume's in
    # tests/integrators/test_spectral_and_mono.py; here sparse against dense only
    check_ref = not mi.is_spectral
    if interpolation == "nearest":
        assert np.array_equal(a, b)
        assert not check_ref or np.allclose(b, ref, rtol=1e-6, atol=0)
    else:
        assert not check_ref or np.max(np.abs(b - ref)) <= 2e-6 * np.max(ref), \
            np.max(np.abs(b - ref))
        hardware = mi.variant().startswith("cuda")
        assert np.max(np.abs(a - b)) <= (3 * 2.0 ** -9 if hardware else 2e-6) * np.max(a)
    assert np.count_nonzero(np.any(a != 0, axis=0)) > 300     # the points do see the data


@pytest.mark.parametrize("interpolation", ["trilinear", "nearest"])
def test_brick_majorants_bound_every_lookup(tmp_path, monkeypatch, interpolation):
    """Bounds from the bricks' extrema (the large-grid path, forced here): along every
    majorant segment of 4096 random rays, sigma_t at 8 random points <= the segment's
    majorant; and empty bricks give empty cells."""
    monkeypatch.setattr(stores, "EXACT_MAJORANT_VOXELS", 0)
    n = 64
    c = (np.arange(n) + 0.5) / n - 0.5
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    r = np.sqrt(x * x + y * y + z * z)
    data = np.where(np.abs(r - 0.3) < 0.05, 4.0, 0.0).astype(np.float32)[..., None]
    data[5, 60, 9] = 9.0
    gridio.write_vol(tmp_path / "shell.vol", data)
    medium = mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / "shell.vol"),
                           "storage": "sparse", "scale": 3.0, "interpolation": interpolation,
                           "majorant_resolution": 64,
                           "to_world": mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)})
    grid = medium.majorant_grid
    assert grid.resolution == (8, 8, 8)      # capped at 8 bricks per axis
    check_segment_bounds(medium, grid)
    assert grid.empty_fraction() > 0.2


def test_storage_choice_and_errors(tmp_path):
    rng = np.random.default_rng(2)
    sparse_data = _random_grid((64, 64, 64, 1), 0.0, rng)
    sparse_data[10:14, 20:30, 40:44] = 1.0
    gridio.write_vol(tmp_path / "s.vol", sparse_data)
    gridio.write_vol(tmp_path / "d.vol", np.ones((16, 16, 16, 1), np.float32))
    auto = mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / "s.vol"),
                         "storage": "auto"})
    assert auto.storage == "sparse" and "storage = sparse" in str(auto)
    assert auto.sparse.nbytes < 0.1 * 4 * 64 ** 3
    full = mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / "d.vol"),
                         "storage": "auto"})
    assert full.storage == "dense" and full.sparse is None
    default = mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / "s.vol")})
    assert default.storage == "dense"           # .vol / .npy default: dense, as before
    with pytest.raises(Exception, match=r"'storage' = 'bricks' is invalid; allowed: dense \| "
                                        r"sparse \| auto"):
        mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / "s.vol"),
                      "storage": "bricks"})
    with pytest.raises(Exception, match="'storage' applies to a 'filename' grid"):
        mi.load_dict({"type": "grid_medium", "storage": "sparse"})


def test_traverse_and_update(tmp_path):
    """Sparse storage exposes scale, sigma_t and the pool as ``bricks`` (no dense
    ``data``); a changed scale rescales the majorants and the render follows (same as
    loading with that scale). The majorant cells are given: chosen automatically, an edit
    keeps the load's choice (no new kernels in an optimisation loop) while a load at the
    new scale may choose others, and the two renders would then draw other numbers."""
    spec = grid(filename=SPARSE, storage="sparse", majorant_resolution=16)
    scene = media_scene(spec, sensor=camera(res=8))
    params = mi.traverse(scene)
    keys = [k for k in params.keys() if k.startswith("ball.")]
    assert not any(k.endswith(".data") for k in keys)
    assert any(k.endswith(".bricks") for k in keys)
    key = next(k for k in keys if k.endswith(".scale"))
    params[key] = 2.0
    params.update()
    integrator = {"type": "volpath_delta", "max_depth": 4}
    a = render(scene, integrator, spp=16, seed=4)
    b = render(media_scene({**spec, "scale": 2.0}, sensor=camera(res=8)), integrator,
               spp=16, seed=4)
    assert_same_render(a, b)


def test_edited_bricks_keep_copies_in_step(tmp_path, monkeypatch):
    """Editing ``bricks``: apron and padding copies are re-read from each voxel's owner
    (edits of copies ignored), lookups equal dense storage of the edited grid (a software
    texture, helpers.software_dense_textures: on an H100 the hardware one differed by up
    to 0.031 at values ~5), the majorant follows, and bad values or a changed shape are
    refused by name."""
    software_dense_textures(monkeypatch)
    rng = np.random.default_rng(1)
    data = np.zeros((20, 13, 17, 1), np.float32)
    data[3:15, 2:11, 5:17] = rng.uniform(0.0, 4.0, (12, 9, 12, 1))
    gridio.write_vol(tmp_path / "g.vol", data)
    medium = mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / "g.vol"),
                           "storage": "sparse"})
    params = mi.traverse(medium)
    before = float(medium.global_majorant[0])
    pool = np.array(params["bricks"])
    edited = pool.copy()
    edited[1:, :8, :8, :8] *= 2.0          # owners: every brick's own voxels
    # slot 1 is brick (0, 0, 0); its x apron holds voxels of the stored brick (0, 0, 1):
    # copies, ignored (the z apron of brick row 1 owns the voxels of the empty row 2)
    assert medium.sparse.index_host[0, 0, 0] == 1 and medium.sparse.index_host[0, 0, 1]
    edited[1, :, :, 8] = 123.0
    params["bricks"] = mi.TensorXf(edited)
    params.update()
    assert np.array_equal(medium.sparse.densify(np.array(medium.sparse.pool)), 2 * data)
    dense = mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / "g.vol"),
                          "storage": "dense", "scale": 2.0})
    points = rng.uniform(-0.1, 1.1, (2000, 3))
    np.testing.assert_allclose(medium_at(medium, "eval_sigma_t", points),
                               medium_at(dense, "eval_sigma_t", points), rtol=1e-5, atol=1e-5)
    assert float(medium.global_majorant[0]) == pytest.approx(2 * before, rel=1e-3)
    edited[1, 0, 0, 0] = np.nan
    params["bricks"] = mi.TensorXf(edited)
    with pytest.raises(Exception, match="parameter 'bricks' holds 1 non-finite"):
        params.update()
    params["bricks"] = mi.TensorXf(pool[:2])
    with pytest.raises(Exception, match="parameter 'bricks' changed shape"):
        params.update()


@pytest.mark.parametrize("integrator", ["volpath_delta", "volpath_raymarch", "volpath"])
@pytest.mark.parametrize("scene_file", ["smoke", "sparse"])
def test_sparse_renders_what_dense_renders(integrator, scene_file):
    """The same grid stored dense and sparse: the same image (docs/validation.md's checks,
    disjoint seeds). volpath sees the global majorant and get_scattering_coefficients
    only, so with the same seed it is the same render up to float rounding of the
    interpolation weights."""
    path = {"smoke": SMOKE, "sparse": SPARSE}[scene_file]
    spec = {"type": integrator, "max_depth": 8}
    if integrator == "volpath_raymarch":
        spec["step_size"] = 0.02
    scenes = [media_scene(grid(filename=path, storage=s), sensor=camera(res=16))
              for s in ("sparse", "dense")]
    a = estimate(scenes[0], spec, passes=8, spp=32, seed=1000)
    b = estimate(scenes[1], spec, passes=8, spp=32, seed=0)
    assert_same_expectation(a, b, f"sparse_vs_dense_{integrator}_{scene_file}")
    if integrator == "volpath":
        same = [render(s, spec, spp=16, seed=9) for s in scenes]
        assert np.mean(np.abs(same[0] - same[1]) > 1e-4) < 0.01


def test_prbvolpath_renders_sparse_storage():
    """Mitsuba's prbvolpath (a Python integrator; our NaN-counting wrapper does not fit
    its signature, so plain mi.render): dense and sparse storage with the same seed give
    the same image up to float rounding in a few paths."""
    scenes = [media_scene(grid(filename=SPARSE, storage=s), sensor=camera(res=16))
              for s in ("sparse", "dense")]
    integrator = mi.load_dict({"type": "prbvolpath", "max_depth": 8})
    a, b = (np.array(mi.render(s, integrator=integrator, spp=64, seed=3)) for s in scenes)
    assert np.all(np.isfinite(a)) and a.mean() > 0.05
    assert np.mean(np.abs(a - b) > 1e-4) < 0.01 and abs(a.mean() / b.mean() - 1) < 1e-3
