""".vdb files as other tools write them (issue 24): several grids of one name, files
without a density grid, empty stretches, extreme indices, wide flat boxes, truncated
files, grid types that cannot be read, 3-channel conversion, and a reader that is bounded
in memory and time and dies with its parent. Files are written by OpenVDB itself
(``pyopenvdb`` in Debian's Python), or crafted from such files where pyopenvdb cannot
write the case (an int32 or vec3d grid: only the type name in the header differs)."""
from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import mitsuba as mi
import numpy as np
import pytest

from helpers import SCENES, make_vdb, medium_at
from mitsuba_plugins.grids import gridio, vdb_header, vdb_openvdb
from mitsuba_plugins.tools import cli

VALUES = (1.0, 5.0, 50.0)


@pytest.fixture(scope="module")
def multi(tmp_path_factory):
    """Three float grids all named 'density' (values 1, 5, 50 on different voxels) and a
    'temperature' grid."""
    path = tmp_path_factory.mktemp("multi") / "multi.vdb"
    make_vdb(path, f"""
        for k, v in enumerate({VALUES}):
            g = vdb.FloatGrid(); g.name = "density"
            g.fill((0, 0, k), (3, 2, k + 1), v, active=True); grids.append(g)
        t = vdb.FloatGrid(); t.name = "temperature"
        t.getAccessor().setValueOn((1, 1, 1), 900.0); grids.append(t)
    """)
    return path


def _openvdb_box(path, address, lo, shape) -> np.ndarray:
    """What OpenVDB's own copyToArray reads from grid ``address`` over the box at index
    ``lo`` of ``shape`` (Z, Y, X), as (Z, Y, X)."""
    script = textwrap.dedent(f"""
        import pyopenvdb as vdb, numpy as np, sys
        g = vdb.read({str(path)!r}, {address!r})
        a = np.zeros({tuple(reversed(shape))}, np.float32)
        g.copyToArray(a, ijk={tuple(lo)})
        np.save(sys.stdout.buffer, a.transpose(2, 1, 0))
    """)
    proc = subprocess.run([vdb_openvdb.DEFAULT_PYTHON, "-c", script], capture_output=True)
    assert proc.returncode == 0, proc.stderr.decode()
    return np.load(io.BytesIO(proc.stdout))


def test_several_grids_of_one_name_are_addressed_and_read_as_openvdb_reads_them(multi):
    entries = vdb_header.read_grid_list(multi)
    assert [e.address for e in entries] == ["density[0]", "density[1]", "density[2]",
                                            "temperature"]
    with pytest.raises(gridio.GridFileError, match=r"3 grids are named 'density'; choose one "
                                                   r"by its address: 'density\[0\]', "
                                                   r"'density\[1\]', 'density\[2\]'"):
        gridio.read_header(multi)
    for k, value in enumerate(VALUES):
        header = gridio.read_header(multi, f"density[{k}]")
        data, _ = gridio.read_grid(multi, grid=f"density[{k}]")
        expected = _openvdb_box(multi, f"density[{k}]", header.index_min, header.shape[:3])
        np.testing.assert_array_equal(data[..., 0], expected)
        assert data.max() == value and np.count_nonzero(data) == 4 * 3 * 2
        medium = mi.load_dict({"type": "grid_medium", "filename": str(multi),
                               "grid": f"density[{k}]", "storage": "sparse"})
        assert float(medium.global_majorant[0]) == pytest.approx(value, rel=1e-5)


def test_grid_info_lists_every_grid_by_address(multi, capsys):
    """Without --grid the ambiguous 'density' is not read: the grids are listed (exit 0),
    with the reason; --grid density[2] reads that grid."""
    assert cli.main(["grid", "info", str(multi)]) == 0
    text = capsys.readouterr().out
    for address in ("density[0]", "density[1]", "density[2]", "temperature"):
        assert f"grid '{address}'" in text
    assert "3 grids are named 'density'" in text and "--grid ADDRESS" in text
    assert cli.main(["grid", "info", str(multi), "--grid", "density[2]", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["grid"] == "density[2]" and info["max"] == 50.0 and info["min"] == 0.0
    assert [g["max"] for g in info["vdb_grids"]] == [*VALUES, 900.0]


def test_grid_convert_reads_the_addressed_grid(multi, tmp_path, capsys):
    assert cli.main(["grid", "convert", str(multi), str(tmp_path / "d1.npy"),
                     "--grid", "density[1]"]) == 0
    assert np.load(tmp_path / "d1.npy").max() == 5.0
    assert cli.main(["grid", "convert", str(multi), str(tmp_path / "d.npy")]) == 2
    assert "3 grids are named 'density'" in capsys.readouterr().err
    assert not (tmp_path / "d.npy").exists()


def test_grid_info_without_density_lists_the_grids(tmp_path, capsys):
    make_vdb(tmp_path / "fire.vdb", """
        for name in ("temperature", "flames"):
            g = vdb.FloatGrid(); g.name = name
            g.getAccessor().setValueOn((0, 0, 0), 2.0); grids.append(g)""")
    assert cli.main(["grid", "info", str(tmp_path / "fire.vdb")]) == 0
    out = capsys.readouterr().out
    assert "grid 'temperature'" in out and "grid 'flames'" in out
    assert "no grid named 'density'" in out
    # asked for by name, a missing grid is an error that lists the file's grids
    assert cli.main(["grid", "info", str(tmp_path / "fire.vdb"), "--grid", "smoke"]) == 1
    assert "'temperature', 'flames'" in capsys.readouterr().err


@pytest.mark.parametrize("storage", ["sparse", "dense"])
def test_empty_stretches_and_empty_grids_load(tmp_path, storage):
    """Two puffs stacked in z with empty brick rows between, a grid without active voxels,
    and a box of active zeros: every storage loads them (an empty brick row once crashed
    the value checks)."""
    make_vdb(tmp_path / "puffs.vdb", """
        g = vdb.FloatGrid(); g.name = "density"
        g.fill((0, 0, 0), (5, 5, 5), 2.0, active=True)
        g.fill((0, 0, 40), (5, 5, 45), 3.0, active=True); grids.append(g)""")
    make_vdb(tmp_path / "empty.vdb", """
        g = vdb.FloatGrid(); g.name = "density"; grids.append(g)""")
    make_vdb(tmp_path / "zeros.vdb", """
        g = vdb.FloatGrid(); g.name = "density"
        g.fill((0, 0, 0), (63, 63, 63), 0.0, active=True); grids.append(g)""")
    puffs = mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / "puffs.vdb"),
                          "storage": storage})
    assert float(puffs.global_majorant[0]) == pytest.approx(3.0, rel=1e-5)
    for name in ("empty.vdb", "zeros.vdb"):
        medium = mi.load_dict({"type": "grid_medium", "filename": str(tmp_path / name),
                               "storage": storage})
        assert float(medium.global_majorant[0]) == 0.0
        assert np.all(medium_at(medium, "eval_sigma_t", [[0.0, 0.0, 0.0]]) == 0.0)


@pytest.mark.parametrize("index", [-(1 << 30) - 1, 1 << 30])
def test_indices_beyond_openvdbs_range_are_refused_at_once(tmp_path, index):
    make_vdb(tmp_path / "far.vdb", f"""
        g = vdb.FloatGrid(); g.name = "density"
        g.getAccessor().setValueOn(({index}, 0, 0), 1.0); grids.append(g)""")
    t0 = time.perf_counter()
    with pytest.raises(gridio.GridFileError, match=r"allowed: indices in \[-2\^30"):
        gridio.read_header(tmp_path / "far.vdb")
    assert time.perf_counter() - t0 < 30


def test_truncated_and_foreign_type_files_give_one_line(tmp_path):
    make_vdb(tmp_path / "two.vdb", """
        for name in ("density", "temperature"):
            g = vdb.FloatGrid(); g.name = name
            g.getAccessor().setValueOn((1, 2, 3), 2.0); grids.append(g)
        v = vdb.Vec3SGrid(); v.name = "color"
        v.getAccessor().setValueOn((0, 0, 0), (1.0, 2.0, 3.0)); grids.append(v)""")
    raw = (tmp_path / "two.vdb").read_bytes()
    (tmp_path / "cut.vdb").write_bytes(raw[:100])
    with pytest.raises(gridio.GridFileError, match="cut.vdb': not a readable OpenVDB file"):
        gridio.read_header(tmp_path / "cut.vdb")
    # the same file with its first grid declared int32 and its colour grid vec3d
    crafted = raw.replace(b"Tree_float_5_4_3", b"Tree_int32_5_4_3", 1)
    crafted = crafted.replace(b"Tree_vec3s_5_4_3", b"Tree_vec3d_5_4_3", 1)
    (tmp_path / "types.vdb").write_bytes(crafted)
    with pytest.raises(gridio.GridFileError,
                       match="grid 'density' holds int32 values; allowed: float, half, vec3s"):
        gridio.read_header(tmp_path / "types.vdb")
    with pytest.raises(gridio.GridFileError, match="grid 'color' holds vec3d values"):
        gridio.read_header(tmp_path / "types.vdb", "color")
    data, _ = gridio.read_grid(tmp_path / "types.vdb", grid="temperature")
    assert data.max() == 2.0                     # the other grids still read
    listed = {g["address"]: g for g in vdb_openvdb.vdb_info(tmp_path / "types.vdb")}
    assert not listed["density"]["readable"] and listed["temperature"]["readable"]


def test_a_level_set_is_refused_with_a_hint(tmp_path):
    make_vdb(tmp_path / "sphere.vdb", """
        g = vdb.createLevelSetSphere(radius=2.0, voxelSize=0.5); g.name = "density"
        grids.append(g)""")
    with pytest.raises(gridio.GridFileError, match="is a level set; allowed: a fog volume"):
        gridio.read_header(tmp_path / "sphere.vdb")


def test_a_wide_flat_grid_loads_in_bounded_reader_memory(tmp_path):
    """Two voxels, at (0, 0, 0) and (8000, 8000, 0): a box of 8003 x 8003 x 3 that the
    reader once copied a whole brick row of (8003^2 x 9 floats plus a transposed copy, over
    3 GB). Cut in tiles, the reader stays within its memory cap, here 1 GiB, and the
    bricks hold both voxels."""
    make_vdb(tmp_path / "flat.vdb", """
        g = vdb.FloatGrid(); g.name = "density"
        a = g.getAccessor(); a.setValueOn((0, 0, 0), 1.0); a.setValueOn((8000, 8000, 0), 2.0)
        grids.append(g)""")
    script = textwrap.dedent(f"""
        import mitsuba_plugins, resource, sys
        from mitsuba_plugins.grids import gridio, vdb_openvdb
        from mitsuba_plugins.grids.bricks import BrickBuilder
        header = gridio.read_header({str(tmp_path / 'flat.vdb')!r})
        builder = BrickBuilder(header.shape)
        for row, cols, blocks in vdb_openvdb.iter_vdb_bricks(header):
            builder.add_row(row, cols, blocks)
        maxima, _ = builder.extrema()
        print(builder.stored - 1, float(maxima.max()),
              resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
    """)
    env = dict(os.environ, **{vdb_openvdb.MEMORY_VARIABLE: str(1 << 30)})
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    stored, top, child_kib = proc.stdout.split()
    assert int(stored) == 2 and float(top) == 2.0
    assert int(child_kib) < 1024 * 1024, f"reader peak {int(child_kib) / 1024:.0f} MiB"


def test_the_readers_memory_cap_gives_one_line(tmp_path, monkeypatch):
    """A grid whose tree (64 MiB of leaves) does not fit the reader's cap (96 MiB: OpenVDB
    itself takes about 50) fails with one line, as a corrupt file that makes OpenVDB
    allocate without bound would."""
    make_vdb(tmp_path / "block.vdb", """
        g = vdb.FloatGrid(); g.name = "density"
        g.copyFromArray(np.random.default_rng(0).random((256, 256, 256), np.float32) + 1)
        grids.append(g)""")
    monkeypatch.setenv(vdb_openvdb.MEMORY_VARIABLE, str(96 << 20))
    with pytest.raises(gridio.GridFileError, match="block.vdb': .*out of memory .*limit 96 MiB"):
        gridio.read_grid(tmp_path / "block.vdb")


def _stuck(tmp_path):
    """A reader that waits for ever: the worker's ``write`` reading its voxels from a
    named pipe whose writing end the test holds open and never writes to. Returns the
    worker's arguments and the pipe's path."""
    fifo = tmp_path / "voxels.fifo"
    os.mkfifo(fifo)
    argv = ["write", str(tmp_path / "out.vdb"), "density", 4, 4, 4, 1,
            *[1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0]]
    return argv, fifo


def test_a_reader_that_sends_nothing_is_stopped(tmp_path, monkeypatch):
    argv, fifo = _stuck(tmp_path)
    holder = os.open(fifo, os.O_RDWR)          # keeps the pipe open, never writes
    try:
        monkeypatch.setenv(vdb_openvdb.TIMEOUT_VARIABLE, "1")
        with open(fifo, "rb") as voxels:
            worker = vdb_openvdb._Worker(tmp_path / "out.vdb", argv, stdin=voxels)
        t0 = time.perf_counter()
        with pytest.raises(gridio.GridFileError, match="sent nothing for 1 s and was stopped"):
            worker.read_line()
        assert time.perf_counter() - t0 < 20 and worker.proc.poll() is not None
    finally:
        os.close(holder)


def test_the_reader_dies_with_its_parent(tmp_path):
    """A parent killed (as by a crash, or Ctrl-C's immediate exit) takes its reader along:
    a reader stuck for ever would otherwise stay behind, adopted by init."""
    argv, fifo = _stuck(tmp_path)
    holder = os.open(fifo, os.O_RDWR)
    script = textwrap.dedent(f"""
        import mitsuba_plugins, time
        from mitsuba_plugins.grids import vdb_openvdb
        with open({str(fifo)!r}, "rb") as voxels:
            w = vdb_openvdb._Worker({str(tmp_path / "out.vdb")!r}, {argv!r}, stdin=voxels)
        time.sleep(2.0)                      # the worker has set its limits by now
        print(w.proc.pid, flush=True)
        time.sleep(60)
    """)
    try:
        parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE,
                                  text=True)
        reader = int(parent.stdout.readline())
        assert _alive(reader)
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        deadline = time.time() + 10
        while _alive(reader) and time.time() < deadline:
            time.sleep(0.1)
        assert not _alive(reader), "the reader outlived its parent"
    finally:
        os.close(holder)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


def test_grid_convert_never_drops_a_grid(multi, tmp_path, capsys):
    """Issue 46.5: ``grid convert f.vdb f.vdb`` kept one grid and dropped the others
    (the fire file lost 'temperature'), and converting onto any multi-grid .vdb replaced
    it without a word. Refused in one line, the file untouched; a one-grid .vdb and a
    new file are still written."""
    import shutil
    target = tmp_path / "multi.vdb"
    shutil.copy(multi, target)
    before = target.read_bytes()
    for source in (target, SCENES / "data" / "smoke.vol"):
        assert cli.main(["grid", "convert", str(source), str(target),
                         "--grid", "density[1]"]) == 2
        err = capsys.readouterr().err
        assert "holds the grid(s) 'density[0]', 'density[1]', 'density[2]', " \
               "'temperature'" in err and "the others would be lost" in err, err
        assert target.read_bytes() == before
    fire = tmp_path / "fire.vdb"
    shutil.copy(SCENES / "data" / "fire.vdb", fire)
    assert cli.main(["grid", "convert", str(fire), str(fire)]) == 2
    assert "'temperature'" in capsys.readouterr().err
    one = tmp_path / "one.vdb"
    assert cli.main(["grid", "convert", str(multi), str(one), "--grid", "temperature"]) == 0
    assert cli.main(["grid", "convert", str(one), str(one), "--grid", "temperature"]) == 0
    assert [g.name for g in vdb_header.read_grid_list(one)] == ["temperature"]


def test_a_three_channel_grid_converts_to_vdb_and_back(tmp_path, capsys):
    source = SCENES / "data" / "chromatic.vol"
    assert cli.main(["grid", "convert", str(source), str(tmp_path / "c.vdb")]) == 0
    assert [g.value_type for g in vdb_header.read_grid_list(tmp_path / "c.vdb")] == ["vec3s"]
    original, _ = gridio.read_grid(source)
    back, _ = gridio.read_grid(tmp_path / "c.vdb")
    # the .vdb's active box: the non-zero voxels, plus one voxel of background around
    nz = np.argwhere(np.any(original > 0, axis=3))
    lo, hi = nz.min(axis=0), nz.max(axis=0)
    np.testing.assert_array_equal(back[1:-1, 1:-1, 1:-1],
                                  original[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1])


@pytest.mark.parametrize("chunk", [4096, 40000])
def test_tiles_and_bands_read_what_whole_rows_read(tmp_path, monkeypatch, chunk):
    """The reader cut into tiny tiles (brick rows) and bands (slices) reads the same
    values and the same bricks as in one piece: a random grid with empty space, 3
    channels, a box that is no multiple of 8."""
    from mitsuba_plugins.grids.bricks import BrickBuilder
    rng = np.random.default_rng(4)
    values = rng.random((37, 29, 23, 3)).astype(np.float32)
    values[5:20, :, 3:11] = 0.0
    make_vdb(tmp_path / "rgb.vdb", """
        g = vdb.Vec3SGrid(); g.name = "density"
        g.copyFromArray(np.ascontiguousarray(values.transpose(2, 1, 0, 3)), ijk=(-4, 2, 9))
        grids.append(g)""", values=values)

    def read():
        header = gridio.read_header(tmp_path / "rgb.vdb")
        data, _ = gridio.read_grid(tmp_path / "rgb.vdb")
        builder = BrickBuilder(header.shape)
        for row, cols, blocks in vdb_openvdb.iter_vdb_bricks(header):
            builder.add_row(row, cols, blocks)
        return data, builder.finish()
    whole, (index, pool, _, _) = read()
    np.testing.assert_array_equal(whole[1:-1, 1:-1, 1:-1], values)
    monkeypatch.setenv("MITSUBA_PLUGINS_VDB_CHUNK", str(chunk))
    cut, (cut_index, cut_pool, _, _) = read()
    np.testing.assert_array_equal(cut, whole)
    np.testing.assert_array_equal(cut_index, index)
    np.testing.assert_array_equal(cut_pool, pool)



@pytest.fixture(scope="module")
def two_far_voxels(tmp_path_factory):
    """Two voxels 2100 apart on each axis: an active box of 2103^3 = 9.3e9 voxels (over
    2^32) that two bricks hold."""
    path = tmp_path_factory.mktemp("far") / "far.vdb"
    make_vdb(path, """
        g = vdb.FloatGrid(); g.name = "density"
        a = g.getAccessor(); a.setValueOn((0, 0, 0), 1.0); a.setValueOn((2100, 2100, 2100), 2.0)
        grids.append(g)""")
    return path


def test_a_huge_sparse_box_loads_sparse_and_dense_is_refused_with_the_size(
        two_far_voxels, monkeypatch):
    """Issue 46: storage = 'dense' on a small .vdb whose two voxels span a huge box
    allocated gigabytes without a word; sparse storage refused an active box over 2^32
    voxels although two bricks hold it, speaking of "a dense grid"."""
    from mitsuba_plugins.grids import value_checks
    medium = mi.load_dict({"type": "grid_medium", "filename": str(two_far_voxels),
                           "storage": "sparse"})
    assert medium.storage == "sparse" and medium.sparse.stored - 1 <= 8
    assert mi.load_dict({"type": "grid_medium", "filename": str(two_far_voxels)}).storage \
        == "sparse"
    monkeypatch.setattr(value_checks, "machine_memory", lambda: 16e9)
    with pytest.raises(Exception, match=r"storage = 'dense' would allocate 37.2 GB for the "
                                        r"2103 x 2103 x 2103 x 1 box of .*allowed: at most 4 GB"
                                        r" here .* use storage = 'sparse'"):
        mi.load_dict({"type": "grid_medium", "filename": str(two_far_voxels),
                      "storage": "dense"})
    # what reads it densely says why, and what to use
    with pytest.raises(gridio.GridFileError, match="a dense grid holds at most 2\\^32 - 1 .*"
                                                   "storage = 'sparse' holds only its bricks"):
        gridio.read_grid(two_far_voxels)
