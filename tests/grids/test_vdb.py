"""OpenVDB input (issue 13, first part): placement by the file's index-to-world transform,
half floats, tiles, negative indices, vector grids, refusals, and the same image as the
same data stored as ``.vol``. The tests write their own small ``.vdb`` files with
``pyopenvdb`` in Debian's Python (``python3-openvdb``, installed by ``.ci/setup``)."""
from __future__ import annotations

import json
import sys

import mitsuba as mi
import numpy as np
import pytest

from helpers import (SMOKE, assert_same_expectation, camera, emitted_in_variant, estimate,
                     make_vdb, media_scene, medium_at)
from mitsuba_plugins.grids import gridio, vdb_openvdb
from mitsuba_plugins.tools import cli


def sigma_t_at(medium, points) -> np.ndarray:
    return medium_at(medium, "eval_sigma_t", points)[0]


def load_medium(path, **kw):
    return mi.load_dict({"type": "grid_medium", "filename": str(path), **kw})


TRANSFORMS = {
    "uniform": "t = vdb.createLinearTransform(0.25)",
    "rotated_scaled_translated": """
        t = vdb.createLinearTransform(0.2)
        t.scale((1.0, 2.5, 0.5)); t.rotate(0.7, vdb.Axis.Y); t.rotate(-0.4, vdb.Axis.X)
        t.translate((0.3, -1.2, 2.0))""",
}


@pytest.mark.parametrize("transform", list(TRANSFORMS))
def test_one_voxel_lands_where_index_to_world_says(tmp_path, transform):
    """Voxel (-3, 2, 5) of value 4: 4 at its world centre, 0 at its neighbours' centres,
    2 half-way (trilinear towards the 0 background), on rotated, non-uniformly scaled,
    translated transforms with negative indices; to_world applies on top."""
    out = make_vdb(tmp_path / "one.vdb", TRANSFORMS[transform], """
        g = vdb.FloatGrid(); g.name = "density"; g.transform = t
        g.getAccessor().setValueOn((-3, 2, 5), 4.0)
        grids.append(g)
        out["centre"] = t.indexToWorld((-3, 2, 5))
        out["neighbours"] = [t.indexToWorld(c) for c in
                             [(-4, 2, 5), (-2, 2, 5), (-3, 1, 5), (-3, 3, 5), (-3, 2, 4), (-3, 2, 6)]]
    """)
    centre, neighbours = np.array(out["centre"]), np.array(out["neighbours"])
    medium = load_medium(tmp_path / "one.vdb")
    np.testing.assert_allclose(sigma_t_at(medium, [centre]), [4.0], rtol=1e-5)
    np.testing.assert_allclose(sigma_t_at(medium, neighbours), 0.0, atol=1e-5)
    np.testing.assert_allclose(sigma_t_at(medium, (neighbours + centre) / 2), 2.0, rtol=1e-4)
    moved = load_medium(tmp_path / "one.vdb",
                        to_world=mi.ScalarTransform4f().translate([1.0, -2.0, 0.5]))
    np.testing.assert_allclose(sigma_t_at(moved, [centre + [1.0, -2.0, 0.5]]), [4.0], rtol=1e-5)


def test_asymmetric_block_round_trip(tmp_path):
    """A random 6 x 5 x 4 block copied in at index (-2, 3, -5): read back exactly, with one
    voxel of background (0) around it; (Z, Y, X) order as for .vol."""
    rng = np.random.default_rng(13)
    block = rng.uniform(0.5, 2.0, (6, 5, 4)).astype(np.float32)   # (i, j, k)
    make_vdb(tmp_path / "b.vdb", """
        g = vdb.FloatGrid(); g.name = "density"
        g.copyFromArray(block, ijk=(-2, 3, -5)); grids.append(g)
    """, block=block)
    data, bbox = gridio.read_grid(tmp_path / "b.vdb")
    assert data.shape == (4 + 2, 5 + 2, 6 + 2, 1) and bbox is None
    np.testing.assert_array_equal(data[1:-1, 1:-1, 1:-1, 0], block.transpose(2, 1, 0))
    interior = np.zeros(data.shape[:3], bool)
    interior[1:-1, 1:-1, 1:-1] = True
    assert np.all(data[~interior] == 0)
    header = gridio.read_header(tmp_path / "b.vdb")
    assert header.index_min == (-3, 2, -6)


def test_half_floats_tiles_and_vectors(tmp_path):
    make_vdb(tmp_path / "m.vdb", """
        h = vdb.FloatGrid(); h.name = "half"; h.saveFloatAsHalf = True
        h.getAccessor().setValueOn((1, 1, 1), 0.3333)
        t = vdb.FloatGrid(); t.name = "tiles"
        t.fill((0, 0, 0), (255, 15, 15), 2.0, active=True)   # 256x16x16: tiles, not voxels
        v = vdb.Vec3SGrid(); v.name = "rgb"
        v.getAccessor().setValueOn((0, 0, 0), (1.0, 2.0, 3.0))
        grids.extend([h, t, v])
    """)
    half, _ = gridio.read_grid(tmp_path / "m.vdb", grid="half")
    assert abs(half.max() - 0.3333) < 1e-3          # stored as half: 1e-3 relative
    tiles, _ = gridio.read_grid(tmp_path / "m.vdb", grid="tiles")
    assert tiles.shape == (18, 18, 258, 1)
    assert np.all(tiles[1:-1, 1:-1, 1:-1] == 2.0) and tiles.sum() == 2.0 * 256 * 16 * 16
    rgb, _ = gridio.read_grid(tmp_path / "m.vdb", grid="rgb")
    assert rgb.shape == (3, 3, 3, 3)
    np.testing.assert_array_equal(rgb[1, 1, 1], [1.0, 2.0, 3.0])
    info = {g["name"]: g for g in vdb_openvdb.vdb_info(tmp_path / "m.vdb")}
    assert info["tiles"]["active_voxels"] == 256 * 16 * 16 and info["half"]["half_float"]


@pytest.mark.parametrize("body, message", [
    ("""
        g = vdb.FloatGrid(1.0); g.name = "density"
        g.getAccessor().setValueOn((0, 0, 0), 2.0); grids.append(g)""",
     "grid 'density' has background 1.0; allowed: 0"),
    ("""
        g = vdb.FloatGrid(); g.name = "density"
        g.transform = vdb.createFrustumTransform(xyzMin=(0, 0, 0), xyzMax=(10, 10, 10),
                                                 taper=0.5, depth=2.0)
        g.getAccessor().setValueOn((1, 1, 1), 2.0); grids.append(g)""",
     "NonlinearFrustumMap transform; allowed: an affine (linear) transform, not a frustum"),
    ("""
        g = vdb.FloatGrid(); g.name = "smoke"; grids.append(g)
        g2 = vdb.FloatGrid(); g2.name = "heat"; grids.append(g2)""",
     "no grid named 'density'; the file holds: "),
])
def test_refused_grids_name_the_reason(tmp_path, body, message):
    make_vdb(tmp_path / "bad.vdb", body)
    with pytest.raises(gridio.GridFileError, match="grid file '.*bad.vdb': "):
        gridio.read_header(tmp_path / "bad.vdb")
    with pytest.raises(Exception) as error:
        load_medium(tmp_path / "bad.vdb")
    assert message in cli.user_message(error.value), cli.user_message(error.value)
    if "holds" in message:   # every name, in the file's order
        assert "'smoke'" in cli.user_message(error.value)
        assert "'heat'" in cli.user_message(error.value)


def test_corrupt_and_truncated_files_are_named(tmp_path):
    make_vdb(tmp_path / "good.vdb", """
        g = vdb.FloatGrid(); g.name = "density"
        g.fill((0, 0, 0), (31, 31, 31), 1.0, active=False)
        g.copyFromArray(np.random.default_rng(1).random((32, 32, 32)).astype(np.float32))
        grids.append(g)""")
    raw = (tmp_path / "good.vdb").read_bytes()
    (tmp_path / "cut.vdb").write_bytes(raw[: len(raw) // 2])
    (tmp_path / "junk.vdb").write_bytes(b"not a vdb file" * 100)
    for name in ("cut.vdb", "junk.vdb"):
        with pytest.raises(gridio.GridFileError, match=f"grid file '.*{name}': "):
            data, _ = gridio.read_grid(tmp_path / name)


def test_missing_openvdb_names_the_package(tmp_path, monkeypatch):
    (tmp_path / "x.vdb").write_bytes(b"x")
    monkeypatch.setenv(vdb_openvdb.PYTHON_VARIABLE, sys.executable)   # the venv: no pyopenvdb
    monkeypatch.setenv(vdb_openvdb.READER_VARIABLE, "worker")          # nor the compiled reader
    with pytest.raises(gridio.GridFileError, match="apt-get install -y python3-openvdb"):
        gridio.read_header(tmp_path / "x.vdb")


def test_grid_info_lists_every_grid(tmp_path, capsys):
    make_vdb(tmp_path / "two.vdb", """
        for name, value in (("density", 1.5), ("temperature", 900.0)):
            g = vdb.FloatGrid(); g.name = name
            g.getAccessor().setValueOn((-1, 0, 2), value); grids.append(g)""")
    assert cli.main(["grid", "info", str(tmp_path / "two.vdb")]) == 0
    text = capsys.readouterr().out
    assert "grid 'density' (read)" in text and "grid 'temperature'" in text
    assert cli.main(["grid", "info", str(tmp_path / "two.vdb"), "--json",
                     "--grid", "temperature"]) == 0
    info = json.loads(capsys.readouterr().out, parse_constant=lambda c: pytest.fail(c))
    assert info["grid"] == "temperature" and info["max"] == 900.0
    assert [g["name"] for g in info["vdb_grids"]] == ["density", "temperature"]


def _twins(tmp_path):
    """The smoke grid as .vol (padded with one voxel of 0, placed over [-1, 1]^3 plus the
    pad) and as .vdb (unpadded, voxel centres at the same world points)."""
    data, _ = gridio.read_grid(SMOKE)
    z, y, x, _ = data.shape
    padded = np.pad(data, ((1, 1), (1, 1), (1, 1), (0, 0)))
    gridio.write_vol(tmp_path / "smoke_padded.vol", padded)
    h = 2.0 / np.array([x, y, z])                               # voxel size per axis
    lo = -1.0 - h                                               # the pad's outer face
    vol = {"type": "grid_medium", "filename": str(tmp_path / "smoke_padded.vol"), "scale": 8.0,
           "albedo": 0.85, "to_world": mi.ScalarTransform4f().translate(lo.tolist()).scale(
               (2.0 + 2 * h).tolist())}
    make_vdb(tmp_path / "smoke.vdb", f"""
        g = vdb.FloatGrid(); g.name = "density"
        g.copyFromArray(np.ascontiguousarray(smoke.transpose(2, 1, 0)))
        t = vdb.createLinearTransform(1.0)
        t.scale({tuple(h.tolist())}); t.translate({tuple((-1.0 + h / 2).tolist())})
        g.transform = t; grids.append(g)""", smoke=data[..., 0])
    vdb_medium = {"type": "grid_medium", "filename": str(tmp_path / "smoke.vdb"),
                  "scale": 8.0, "albedo": 0.85}
    return vol, vdb_medium


@pytest.mark.parametrize("integrator", ["volpath_delta", "volpath_raymarch", "volpath"])
def test_vdb_renders_what_the_same_data_as_vol_renders(tmp_path, integrator):
    """The smoke as .vdb stored sparse and as .vol stored dense: same image
    (docs/validation.md's three checks, fixed seeds), with ours and with Mitsuba's volpath
    (which sees the global majorant and get_scattering_coefficients only)."""
    vol, vdb_medium = _twins(tmp_path)
    vdb_medium["storage"] = "sparse"
    spec = {"type": integrator}
    if integrator == "volpath_raymarch":
        spec["step_size"] = 0.02
    a = estimate(media_scene(vdb_medium, sensor=camera(res=16)), spec, passes=16, spp=32,
                 seed=1000)
    b = estimate(media_scene(vol, sensor=camera(res=16)), spec, passes=16, spp=32, seed=0)
    assert_same_expectation(a, b, f"vdb_vs_vol_{integrator}")


# -- grid convert: any format to .vol / .npy, streamed, size announced, atomic ----------------
def test_convert_vdb_to_vol_keeps_placement(tmp_path, capsys):
    """An axis-aligned .vdb (non-uniform voxels, negative offset) converted to .vol: the
    .vol placed by its header box (use_grid_bbox) gives the same extinction as the .vdb
    at 4096 random points in and around the grid; the dense size is printed first."""
    rng = np.random.default_rng(3)
    block = rng.uniform(0.0, 3.0, (7, 5, 6)).astype(np.float32)
    make_vdb(tmp_path / "a.vdb", """
        g = vdb.FloatGrid(); g.name = "density"
        t = vdb.createLinearTransform(1.0); t.scale((0.2, 0.3, 0.25)); t.translate((-0.4, 0.1, 0.3))
        g.transform = t; g.copyFromArray(block, ijk=(-3, 1, -2)); grids.append(g)
    """, block=block)
    assert cli.main(["grid", "convert", str(tmp_path / "a.vdb"), str(tmp_path / "a.vol")]) == 0
    out = capsys.readouterr().out
    assert "a.vol: 9 x 7 x 8 x 1 float32 values" in out and "rotates" not in out
    from_vdb = load_medium(tmp_path / "a.vdb")
    from_vol = load_medium(tmp_path / "a.vol", use_grid_bbox=True)
    lo, hi = np.array(from_vdb.bbox.min), np.array(from_vdb.bbox.max)
    points = rng.uniform(lo - 0.1, hi + 0.1, (4096, 3))
    inside = np.all((points > lo) & (points < hi), axis=1)
    np.testing.assert_allclose(sigma_t_at(from_vol, points[inside]),
                               sigma_t_at(from_vdb, points[inside]), rtol=1e-4, atol=1e-5)


def test_convert_vol_to_npy_and_failures_leave_the_target(tmp_path, capsys):
    data = np.random.default_rng(4).uniform(0, 1, (4, 5, 6, 1)).astype(np.float32)
    gridio.write_vol(tmp_path / "g.vol", data)
    assert cli.main(["grid", "convert", str(tmp_path / "g.vol"), str(tmp_path / "g.npy")]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "g.npy"), data)
    bad = data.copy()
    bad[2, 2, 2, 0] = np.nan
    np.save(tmp_path / "bad.npy", bad)
    (tmp_path / "keep.vol").write_bytes(b"old")
    assert cli.main(["grid", "convert", str(tmp_path / "bad.npy"), str(tmp_path / "keep.vol")]) == 2
    assert "non-finite" in capsys.readouterr().err
    assert (tmp_path / "keep.vol").read_bytes() == b"old"
    assert cli.main(["grid", "convert", str(tmp_path / "g.vol"), str(tmp_path / "g.exr")]) == 2
    assert "extension '.exr' is not supported; allowed: .vol, .npy" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npy", "g.npy", "g.vol", "keep.vol"]


# -- emission_grid --------------------------------------------------------------------------
def radiance_at(medium, points) -> np.ndarray:
    return medium_at(medium, "get_radiance", points)


def test_emission_grid_multiplies_emission_where_its_transform_says(tmp_path):
    """A 'temperature' grid with its own rotated transform and box beside the density:
    radiance = emission x temperature at the temperature voxels' world centres, 0 at a
    neighbour's centre, and emission defaults to 1."""
    out = make_vdb(tmp_path / "fire.vdb", TRANSFORMS["rotated_scaled_translated"], """
        d = vdb.FloatGrid(); d.name = "density"
        d.transform = vdb.createLinearTransform(0.1)
        d.fill((0, 0, 0), (9, 9, 9), 1.0); grids.append(d)
        g = vdb.FloatGrid(); g.name = "temperature"; g.transform = t
        a = g.getAccessor(); a.setValueOn((4, -1, 7), 3.0); a.setValueOn((-6, 2, 0), 0.5)
        grids.append(g)
        out["hot"] = [t.indexToWorld((4, -1, 7)), t.indexToWorld((-6, 2, 0))]
        out["cold"] = [t.indexToWorld((4, 1, 7))]
    """)
    hot, cold = np.array(out["hot"]), np.array(out["cold"])
    medium = load_medium(tmp_path / "fire.vdb", emission_grid="temperature",
                         emission=[2.0, 1.0, 0.5])
    assert medium.has_emission
    emitted = emitted_in_variant([2.0, 1.0, 0.5])
    np.testing.assert_allclose(radiance_at(medium, hot).T, [3.0 * emitted, 0.5 * emitted],
                               rtol=1e-5)
    np.testing.assert_allclose(radiance_at(medium, cold), 0.0, atol=1e-6)
    unit = load_medium(tmp_path / "fire.vdb", emission_grid="temperature")
    np.testing.assert_allclose(radiance_at(unit, hot[:1]).ravel(),
                               3.0 * emitted_in_variant([1.0, 1.0, 1.0]), rtol=1e-5)
    with pytest.raises(Exception, match="no grid named 'flames'; the file holds: 'density', "
                                        "'temperature'"):
        load_medium(tmp_path / "fire.vdb", emission_grid="flames")


def test_emission_grid_needs_a_vdb():
    with pytest.raises(Exception, match="'emission_grid' selects a grid of a .vdb file"):
        mi.load_dict({"type": "grid_medium", "filename": SMOKE, "emission_grid": "t"})


def test_convert_to_vdb_keeps_placement_and_values(tmp_path, capsys):
    """.vol -> .vdb -> .vol: the same values and world box; the .vdb keeps only the
    non-zero voxels; a rotated .vdb -> .vdb keeps its rotation (same extinction at
    random world points)."""
    rng = np.random.default_rng(4)
    data = np.zeros((6, 7, 9, 1), np.float32)
    data[1:4, 2:6, 3:8] = rng.uniform(0.5, 2.0, (3, 4, 5, 1))
    gridio.write_vol(tmp_path / "a.vol", data, bbox=((-1.0, 0.5, 2.0), (2.0, 1.9, 3.2)))
    gridio.convert(tmp_path / "a.vol", tmp_path / "a.vdb", report=lambda line: None)
    info = {g["name"]: g for g in vdb_openvdb.vdb_info(tmp_path / "a.vdb")}
    assert info["density"]["active_voxels"] == 3 * 4 * 5
    gridio.convert(tmp_path / "a.vdb", tmp_path / "b.vol", report=lambda line: None)
    back, bbox = gridio.read_grid(tmp_path / "b.vol")
    np.testing.assert_array_equal(back[1:-1, 1:-1, 1:-1], data[1:4, 2:6, 3:8])
    vox = (np.array([2.0, 1.9, 3.2]) - (-1.0, 0.5, 2.0)) / (9, 7, 6)
    np.testing.assert_allclose(bbox[0], np.array([-1.0, 0.5, 2.0]) + vox * (2, 1, 0), atol=1e-5)
    make_vdb(tmp_path / "r.vdb", TRANSFORMS["rotated_scaled_translated"], """
        g = vdb.FloatGrid(); g.name = "density"; g.transform = t
        g.copyFromArray(block, ijk=(-2, 3, -5)); grids.append(g)
    """, block=rng.uniform(0.5, 2.0, (5, 4, 3)).astype(np.float32))
    gridio.convert(tmp_path / "r.vdb", tmp_path / "r2.vdb", report=lambda line: None)
    a, b = load_medium(tmp_path / "r.vdb"), load_medium(tmp_path / "r2.vdb")
    points = np.array(a.bbox.min) + rng.random((2000, 3)) * (np.array(a.bbox.max) - a.bbox.min)
    np.testing.assert_allclose(sigma_t_at(b, points), sigma_t_at(a, points), atol=1e-5)
