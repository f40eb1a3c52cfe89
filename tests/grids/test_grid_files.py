"""Grid files: .vol/.npy round trips, every malformed input, and `grid info`."""
from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from mitsuba_plugins.grids import gridio
from mitsuba_plugins.tools import cli, grid_info


def _grid(shape=(3, 4, 5), channels=1, seed=0):
    rng = np.random.default_rng(seed)
    return rng.random(shape + (channels,), dtype=np.float32)


@pytest.mark.parametrize("ext", ["vol", "npy"])
@pytest.mark.parametrize("channels", [1, 3])
def test_round_trip(tmp_path, ext, channels):
    data = _grid(channels=channels)
    path = tmp_path / f"g.{ext}"
    bbox = ((-1.0, 0.5, 2.0), (1.0, 1.5, 4.0))
    gridio.write_grid(path, data, bbox)
    back, back_bbox = gridio.read_grid(path)
    assert back.dtype == np.float32 and back.shape == data.shape
    assert np.array_equal(back, data)
    assert back_bbox == (bbox if ext == "vol" else None)


def test_vol_layout_is_mitsubas(tmp_path):
    """Byte layout: header fields and data[((z*Y + y)*X + x)*C + c]."""
    data = _grid((2, 3, 4), channels=3)
    path = tmp_path / "g.vol"
    gridio.write_vol(path, data)
    raw = path.read_bytes()
    assert raw[:4] == b"VOL\x03"
    assert struct.unpack("<iiiii", raw[4:24]) == (1, 4, 3, 2, 3)
    flat = np.frombuffer(raw[48:], dtype="<f4")
    z, y, x, c = 1, 2, 3, 1
    assert flat[((z * 3 + y) * 4 + x) * 3 + c] == data[z, y, x, c]


def test_npy_3d_and_float64(tmp_path):
    data = np.random.default_rng(1).random((2, 3, 4))  # float64, no channel axis
    np.save(tmp_path / "g.npy", data)
    back, bbox = gridio.read_grid(tmp_path / "g.npy")
    assert back.shape == (2, 3, 4, 1) and bbox is None
    assert np.allclose(back[..., 0], data, rtol=1e-7)


def test_slabs_cover_the_grid_in_order(tmp_path):
    data = _grid((37, 5, 6))
    gridio.write_vol(tmp_path / "g.vol", data)
    header = gridio.read_header(tmp_path / "g.vol")
    slabs = list(gridio.iter_slabs(header, slab_bytes=5 * 6 * 4 * 4))  # 4 slices each
    assert [z0 for z0, _ in slabs] == list(range(0, 37, 4))
    assert np.array_equal(np.concatenate([s for _, s in slabs]), data)


def _vol_bytes(magic=b"VOL", version=3, encoding=1, dims=(4, 3, 2), channels=1,
               bbox=(0, 0, 0, 1, 1, 1), values=None):
    x, y, z = dims
    n = max(x * y * z * channels, 0)
    values = np.ones(n, np.float32) if values is None else np.asarray(values, np.float32)
    header = struct.pack("<3sBiiiii6f", magic, version, encoding, x, y, z, channels, *bbox)
    return header + values.astype("<f4").tobytes()


BAD_VOL = {
    "magic": (_vol_bytes(magic=b"VOX"), "not a .vol file"),
    "version": (_vol_bytes(version=2), "unsupported .vol version 2"),
    "encoding": (_vol_bytes(encoding=2), "unsupported encoding 2"),
    "channels": (_vol_bytes(channels=2), "2 channels"),
    "truncated": (_vol_bytes()[:-8], "truncated data"),
    "truncated_header": (_vol_bytes()[:20], "truncated header"),
    "trailing": (_vol_bytes() + b"\0\0\0\0", "trailing data"),
    "too_small": (_vol_bytes(dims=(4, 1, 2)), "at least 2"),
    "zero_dims": (_vol_bytes(dims=(0, 3, 2)), "invalid dimensions"),
    "bbox": (_vol_bytes(bbox=(0, 0, 0, 1, -1, 1)), "invalid bounding box"),
    "nan": (_vol_bytes(values=[1] * 23 + [np.nan]), "non-finite"),
    "inf": (_vol_bytes(values=[np.inf] + [1] * 23), "non-finite"),
    "negative": (_vol_bytes(values=[1] * 10 + [-0.5] + [1] * 13), "negative value -0.5"),
}


@pytest.mark.parametrize("case", sorted(BAD_VOL))
def test_bad_vol(tmp_path, case):
    raw, message = BAD_VOL[case]
    path = tmp_path / f"{case}.vol"
    path.write_bytes(raw)
    with pytest.raises(gridio.GridFileError, match=message) as info:
        gridio.read_grid(path)
    assert str(path) in str(info.value)


def test_bad_npy(tmp_path):
    np.save(tmp_path / "int.npy", np.ones((2, 2, 2), np.int32))
    np.save(tmp_path / "flat.npy", np.ones((8,), np.float32))
    np.save(tmp_path / "small.npy", np.ones((2, 1, 2), np.float32))
    (tmp_path / "junk.npy").write_bytes(b"not numpy at all")
    (tmp_path / "grid.raw").write_bytes(b"")
    cases = {"int.npy": "dtype int32", "flat.npy": "shape", "small.npy": "at least 2",
             "junk.npy": "not a valid .npy", "grid.raw": "unknown extension",
             "missing.vol": "does not exist"}
    for name, message in cases.items():
        with pytest.raises(gridio.GridFileError, match=message):
            gridio.read_grid(tmp_path / name)
    np.save(tmp_path / "trunc.npy", np.ones((4, 4, 4), np.float32))
    raw = (tmp_path / "trunc.npy").read_bytes()
    (tmp_path / "trunc.npy").write_bytes(raw[:-4])
    with pytest.raises(gridio.GridFileError, match="truncated"):
        gridio.read_grid(tmp_path / "trunc.npy")


def test_grid_info(tmp_path, capsys):
    data = np.zeros((32, 32, 32, 1), np.float32)
    data[4:8, 4:8, 4:8] = 2.0  # one dense block in an empty grid
    path = tmp_path / "g.vol"
    gridio.write_vol(path, data, ((0, 0, 0), (2, 2, 2)))
    info = grid_info.grid_info(path, cells=8)
    assert info["resolution"] == [32, 32, 32] and info["channels"] == 1
    assert info["bbox_max"] == [2.0, 2.0, 2.0] and info["bbox_from"] == "header"
    assert info["max"] == 2.0 and info["min"] == 0.0
    assert info["mean"] == pytest.approx(2.0 * 64 / 32 ** 3)
    assert info["max_over_mean"] == pytest.approx(512.0)
    # The block spans cell 1 on each axis (voxels 4-7) and, through the trilinear
    # margin, touches cells 0 and 2: 27 of 512 cells are non-empty.
    assert info["majorant_empty_fraction"] == pytest.approx(1 - 27 / 512)
    assert cli.main(["grid", "info", str(path), "--json", "--majorant-resolution", "8"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["majorant_empty_fraction"] == info["majorant_empty_fraction"]
    assert cli.main(["grid", "info", str(path)]) == 0
    assert "max / mean" in capsys.readouterr().out
    # an unreadable file among others: every file reported, status 1 (issue 24)
    assert cli.main(["grid", "info", str(tmp_path / "none.vol"), str(path)]) == 1
    captured = capsys.readouterr()
    assert "none.vol': file does not exist" in captured.err and "max / mean" in captured.out
