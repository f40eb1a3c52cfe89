"""The compiled leaf-level .vdb reader (``mitsuba_plugins.grids._openvdb_bricks``, issue 27 item
3) against the pyopenvdb worker, the reader proven since issue 13, on files as tools write
them (item 5): Blosc-compressed (OpenVDB's default where it has Blosc, as Debian's has),
half floats, active tiles at several tree levels, inactive voxels holding values,
several grids of one name, vec3 grids, negative and unaligned indices, a box that is no
multiple of a brick. Equal means every stored brick (coordinates and values, bit for
bit) is the same, so every render is too. Zip-compressed and uncompressed files are
written by the extension's ``write`` (OpenVDB's ``io::File`` with the compression set)."""
from __future__ import annotations

import numpy as np
import pytest

from helpers import make_vdb
from mitsuba_plugins.grids import bricks, gridio, vdb_openvdb
from mitsuba_plugins.grids.vdb_header import read_grid_list


def test_the_leaf_reader_is_built():
    """.ci/setup installs libopenvdb-dev, so the install must have built it (a silent
    fallback to the worker would hide a broken build)."""
    assert vdb_openvdb.leaf_reader() is not None


def _bricks(path, grid, monkeypatch, reader):
    monkeypatch.setenv(vdb_openvdb.READER_VARIABLE, reader)
    header = gridio.read_header(path, grid)
    builder = bricks.BrickBuilder(header.shape)
    for row, cols, blocks in vdb_openvdb.iter_vdb_bricks(header):
        builder.add_row(row, cols, blocks)
    index, pool, maxima, minima = builder.finish()
    return header, index, pool, maxima


def _same(path, grid, monkeypatch):
    """The two readers' bricks of ``grid``; returns the stored pool."""
    _, index, pool, maxima = _bricks(path, grid, monkeypatch, "extension")
    _, w_index, w_pool, w_maxima = _bricks(path, grid, monkeypatch, "worker")
    np.testing.assert_array_equal(index, w_index)
    assert pool.tobytes() == w_pool.tobytes()
    np.testing.assert_array_equal(maxima, w_maxima)
    return index, pool


@pytest.fixture(scope="module")
def studio(tmp_path_factory):
    """One file of several grids, the kinds tools write: a random float grid at unaligned
    negative indices with an empty gap; the same saved as half floats; a fill that
    OpenVDB stores as active tiles of 8^3 and 128^3 voxels next to voxels; inactive
    voxels holding non-zero values; a vec3 colour grid; and a second grid named
    'density'."""
    rng = np.random.default_rng(27)
    values = rng.random((29, 21, 19)).astype(np.float32)
    values[4:11] = 0.0
    colour = rng.random((11, 13, 9, 3)).astype(np.float32)
    path = tmp_path_factory.mktemp("studio") / "studio.vdb"
    make_vdb(path, """
        def put(g, name, array, ijk):
            g.name = name
            g.copyFromArray(np.ascontiguousarray(array.transpose(2, 1, 0, *range(3, array.ndim))),
                            ijk=ijk)
            grids.append(g)
            return g
        put(vdb.FloatGrid(), "density", values, (-13, 5, -30))
        put(vdb.FloatGrid(), "smoke_half", values, (3, -7, 1)).saveFloatAsHalf = True
        t = vdb.FloatGrid(); t.name = "tiles"
        t.fill((-128, 0, 0), (-1, 127, 127), 0.25, active=True)   # one 128^3 tile
        t.fill((0, 0, 0), (15, 7, 7), 2.0, active=True)           # two 8^3 tiles
        acc = t.getAccessor()
        acc.setValueOn((20, 3, 3), 7.0)                            # voxels in a leaf
        acc.setValueOff((21, 3, 3), 5.0)                           # inactive, non-zero
        grids.append(t)
        put(vdb.Vec3SGrid(), "Cd", colour, (2, 2, -5))
        second = vdb.FloatGrid(); second.name = "density"
        second.getAccessor().setValueOn((0, 0, 0), 3.0); grids.append(second)
    """, values=values, colour=colour)
    return path, values, colour


def test_the_file_is_what_tools_write(studio):
    path, _, _ = studio
    kinds = {e.address: e.value_type for e in read_grid_list(path)}
    assert kinds == {"density[0]": "float", "smoke_half": "half", "tiles": "float",
                     "Cd": "vec3s", "density[1]": "float"}


@pytest.mark.parametrize("grid", ["density[0]", "smoke_half", "tiles", "Cd", "density[1]"])
def test_leaf_reader_equals_the_worker(studio, monkeypatch, grid):
    _same(studio[0], grid, monkeypatch)


def test_leaf_reader_reads_the_values_written(studio, monkeypatch):
    """Beyond agreeing with the worker: the float grid's values come back exactly, the
    half-float grid's to half precision, tiles expanded, the inactive value kept."""
    path, values, colour = studio
    monkeypatch.setenv(vdb_openvdb.READER_VARIABLE, "extension")
    for grid, expected, tol in (("density[0]", values, 0.0), ("smoke_half", values, 1e-3),
                                ("Cd", colour, 0.0)):
        header = gridio.read_header(path, grid)
        _, index, pool, _ = _bricks(path, grid, monkeypatch, "extension")
        dense = bricks.densify(index, pool, header.shape)[1:-1, 1:-1, 1:-1]
        if expected.ndim == 3:
            dense = dense[..., 0]
        np.testing.assert_allclose(dense, expected, rtol=tol, atol=0)
        if tol:       # stored as half floats indeed: not the float32 values
            assert np.any(dense != expected)
    header = gridio.read_header(path, "tiles")
    _, index, pool, _ = _bricks(path, "tiles", monkeypatch, "extension")
    dense = bricks.densify(index, pool, header.shape)[..., 0]
    lo = np.array(header.index_min)            # (x, y, z) of dense[0, 0, 0]

    def at(i, j, k):
        return dense[k - lo[2], j - lo[1], i - lo[0]]
    assert at(-128, 0, 0) == at(-1, 127, 127) == np.float32(0.25)
    assert at(0, 0, 0) == at(15, 7, 7) == 2.0 and at(16, 0, 0) == 0.0
    assert at(20, 3, 3) == 7.0 and at(21, 3, 3) == 5.0


@pytest.mark.parametrize("compression", ["zip", "none", "blosc"])
@pytest.mark.parametrize("channels,half", [(1, False), (1, True), (3, False)])
def test_each_compression_reads_the_same(tmp_path, monkeypatch, compression, channels, half):
    """Files written by OpenVDB's library with each compression (pyopenvdb always writes
    Blosc; the extension's ``write`` sets ``io::File::setCompression``): both readers
    give the bricks of the values written."""
    rng = np.random.default_rng(5)
    values = rng.random((19, 23, 17, channels)).astype(np.float32) + 0.01
    values[3:9] = 0.0
    path = tmp_path / f"{compression}.vdb"
    vdb_openvdb.leaf_reader().write(str(path), "density", values if channels == 3 else values[..., 0],
                            (-5, 9, 3), 0.05, compression, half)
    index, pool = _same(path, "density", monkeypatch)
    header = gridio.read_header(path)
    dense = bricks.densify(index, pool, header.shape)
    lo = np.array(header.index_min)                       # (x, y, z) of dense[0, 0, 0]
    z0, y0, x0 = (np.array([3, 9, -5]) - lo[::-1]).tolist()
    got = dense[z0:z0 + 19, y0:y0 + 23, x0:x0 + 17]
    np.testing.assert_allclose(got, values, rtol=1e-3 if half else 0.0, atol=0.0)


def test_the_compressions_are_real(tmp_path):
    """The writer's compression is what it says: random values (half of them 0) take
    about 3x less room zipped or with Blosc than uncompressed."""
    values = np.random.default_rng(1).random((40, 40, 40)).astype(np.float32)
    values[values < 0.5] = 0.0
    size = {}
    for compression in ("none", "zip", "blosc"):
        path = tmp_path / f"{compression}.vdb"
        vdb_openvdb.leaf_reader().write(str(path), "density", values, (0, 0, 0), 0.1, compression)
        size[compression] = path.stat().st_size
    assert size["zip"] < 0.5 * size["none"] and size["blosc"] < 0.5 * size["none"], size


def test_a_wrong_reader_choice_is_named(monkeypatch):
    monkeypatch.setenv(vdb_openvdb.READER_VARIABLE, "fast")
    with pytest.raises(ValueError, match="MITSUBA_PLUGINS_VDB_READER.*auto, extension, worker"):
        vdb_openvdb.leaf_reader()
