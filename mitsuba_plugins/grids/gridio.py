"""Read and write density grids: Mitsuba's binary ``.vol`` and NumPy ``.npy``.

Arrays are always ``(Z, Y, X, C)`` float32, C-ordered, so that
``data[z, y, x, c]`` is the value Mitsuba's ``gridvolume`` stores at
``((z * Y + y) * X + x) * C + c``.

``.vol`` layout (little endian; the format ``gridvolume`` reads):

======  ===================================================================
bytes   content
======  ===================================================================
0-2     ASCII ``VOL``
3       version, 3
4-7     encoding (int32), 1 = float32
8-19    X, Y, Z cell counts (int32)
20-23   channel count (int32)
24-47   bounding box (6 x float32: xmin, ymin, zmin, xmax, ymax, zmax)
48-     data, ``X * Y * Z * C`` float32 values
======  ===================================================================

Every reader validates before it returns anything, and a malformed file raises
:class:`GridFileError` naming the file and what is wrong with it.  Large grids are
read in slabs of whole z-slices (:func:`iter_slabs`) so a caller can move them into
device memory without holding a second full copy.
"""
from __future__ import annotations

import os
import re
import struct

import numpy as np

# the header types live in gridheader (vdb.py uses them without importing this module)
from mitsuba_plugins.grids.gridheader import (GRID_CHANNELS, MAX_VALUES, MIN_RESOLUTION,  # noqa: F401
                                        GridFileError, GridHeader, check_regular_file,
                                        check_dense_size, check_shape as _check_shape, check_values,
                                        fail as _fail)

VOL_MAGIC = b"VOL"
VOL_VERSION = 3
VOL_ENCODING_FLOAT32 = 1
VOL_HEADER = struct.Struct("<3sBiiiii6f")  # 48 bytes
#: bytes per slab in :func:`iter_slabs` (whole z-slices, at least one)
SLAB_BYTES = 1 << 20


def read_header(path, grid: str = "density") -> GridHeader:
    """Validate and return the header of a ``.vol``, ``.npy`` or ``.vdb`` grid file
    (``grid``: which grid of a ``.vdb``)."""
    path = os.fspath(path)
    check_regular_file(path)
    ext = os.path.splitext(path)[1].lower()
    if ext == ".vol":
        return _read_vol_header(path)
    if ext == ".npy":
        return _read_npy_header(path)
    if ext == ".vdb":
        from mitsuba_plugins.grids.vdb_openvdb import read_vdb_header
        return read_vdb_header(path, grid)
    _fail(path, f"unknown extension '{ext}'; allowed: .vol (Mitsuba binary grid), .npy "
                "or .vdb (OpenVDB)")


def _read_vol_header(path) -> GridHeader:
    with open(path, "rb") as f:
        raw = f.read(VOL_HEADER.size)
    if len(raw) < VOL_HEADER.size:
        if raw[:3] != VOL_MAGIC[:len(raw[:3])]:
            _fail(path, "not a .vol file (the first bytes are not 'VOL')")
        _fail(path, f"truncated header ({len(raw)} of {VOL_HEADER.size} bytes)")
    magic, version, encoding, x, y, z, c, *bbox = VOL_HEADER.unpack(raw)
    if magic != VOL_MAGIC:
        _fail(path, f"not a .vol file (magic {magic!r}, expected b'VOL')")
    if version != VOL_VERSION:
        _fail(path, f"unsupported .vol version {version}; allowed: {VOL_VERSION}")
    if encoding != VOL_ENCODING_FLOAT32:
        _fail(path, f"unsupported encoding {encoding}; allowed: {VOL_ENCODING_FLOAT32} "
                    "(float32)")
    if min(x, y, z, c) <= 0:
        _fail(path, f"invalid dimensions X={x} Y={y} Z={z} channels={c}")
    shape = (z, y, x, c)
    _check_shape(path, shape)
    lo, hi = tuple(bbox[:3]), tuple(bbox[3:])
    if not (np.all(np.isfinite(bbox)) and all(a < b for a, b in zip(lo, hi))):
        _fail(path, f"invalid bounding box min={lo} max={hi}; needs finite min < max")
    expected = VOL_HEADER.size + 4 * int(np.prod(shape))
    actual = os.path.getsize(path)
    if actual < expected:
        _fail(path, f"truncated data: {actual} bytes, the header announces {expected}")
    if actual > expected:
        _fail(path, f"{actual - expected} bytes of trailing data after the grid "
                    f"(header announces {expected} bytes in all)")
    return GridHeader(path, shape, (lo, hi), VOL_HEADER.size, np.dtype("<f4"))


def _read_npy_header(path) -> GridHeader:
    with open(path, "rb") as f:
        try:
            version = np.lib.format.read_magic(f)
            read = {(1, 0): np.lib.format.read_array_header_1_0,
                    (2, 0): np.lib.format.read_array_header_2_0}.get(version)
            if read is None:
                _fail(path, f".npy format version {version}; allowed: 1.0 or 2.0")
            shape, fortran_order, dtype = read(f)
        except (ValueError, OSError) as error:
            _fail(path, f"not a valid .npy file ({error})")
        offset = f.tell()
    if dtype.kind != "f":
        _fail(path, f"dtype {dtype}; allowed: float32 (or another float type)")
    if len(shape) == 3:
        shape = shape + (1,)
    if len(shape) != 4:
        _fail(path, f"shape {shape}; allowed: (Z, Y, X) or (Z, Y, X, C)")
    _check_shape(path, shape)
    expected = offset + dtype.itemsize * int(np.prod(shape))
    actual = os.path.getsize(path)
    if actual < expected:
        _fail(path, f"truncated data: {actual} bytes, the header announces {expected}")
    return GridHeader(path, tuple(int(s) for s in shape), None, offset, dtype, fortran_order)


def iter_slabs(header: GridHeader, slab_bytes: int = SLAB_BYTES):
    """Yield ``(z0, slab)`` with ``slab`` a float32 ``(k, Y, X, C)`` array of z-slices.

    Reads the file incrementally (one slab in memory at a time) for C-ordered data;
    a Fortran-ordered ``.npy`` is loaded whole first.
    """
    z, y, x, c = header.shape
    if header.vdb_grid is not None:
        from mitsuba_plugins.grids.vdb_openvdb import iter_vdb_slabs
        check_dense_size(header.path, header.shape)    # a .vdb's box may be any size
        yield from iter_vdb_slabs(header, slab_bytes)
        return
    if header.fortran_order:
        data = np.load(header.path).reshape(header.shape)
        for z0 in range(0, z, 1):
            yield z0, np.ascontiguousarray(data[z0:z0 + 1], dtype=np.float32)
        return
    slice_count = y * x * c
    per_slab = max(1, slab_bytes // (4 * slice_count))
    with open(header.path, "rb") as f:
        f.seek(header.offset)
        for z0 in range(0, z, per_slab):
            k = min(per_slab, z - z0)
            count = k * slice_count
            raw = np.fromfile(f, dtype=header.dtype, count=count)
            if raw.size != count:
                _fail(header.path, "truncated data")
            yield z0, raw.astype(np.float32, copy=False).reshape(k, y, x, c)


def read_grid(path, check: bool = True, grid: str = "density") -> tuple:
    """Load a whole grid: ``(data (Z, Y, X, C) float32, bbox or None)``.

    With ``check``, non-finite and negative values raise :class:`GridFileError`.
    """
    header = read_header(path, grid)
    check_dense_size(header.path, header.shape)
    data = np.empty(header.shape, dtype=np.float32)
    for z0, slab in iter_slabs(header):
        if check:
            check_values(header.path, "data", slab)
        data[z0:z0 + slab.shape[0]] = slab
    return data, header.bbox


def as_grid_array(data) -> np.ndarray:
    """``data`` as a float32 ``(Z, Y, X, C)`` array (a 3D array gets C = 1)."""
    data = np.asarray(data, dtype=np.float32)
    if data.ndim == 3:
        data = data[..., None]
    if data.ndim != 4:
        raise GridFileError(f"grid array of shape {data.shape}; allowed: (Z, Y, X) or "
                            "(Z, Y, X, C)")
    return np.ascontiguousarray(data)


def write_vol(path, data, bbox=((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))) -> None:
    """Write ``data`` ((Z, Y, X) or (Z, Y, X, C)) as a version-3 float32 ``.vol``."""
    data = as_grid_array(data)
    z, y, x, c = data.shape
    _check_shape(path, data.shape)
    lo, hi = bbox
    header = VOL_HEADER.pack(VOL_MAGIC, VOL_VERSION, VOL_ENCODING_FLOAT32, x, y, z, c,
                             *map(float, lo), *map(float, hi))
    from mitsuba_plugins.output import atomic_path
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header)
        f.write(data.astype("<f4", copy=False).tobytes())


def write_grid(path, data, bbox=((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))) -> None:
    """Write ``.vol`` or ``.npy`` by extension (``.npy`` stores no bounding box)."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext == ".vol":
        write_vol(path, data, bbox)
    elif ext == ".npy":
        from mitsuba_plugins.output import atomic_path
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.save(f, as_grid_array(data))
    else:
        raise GridFileError(f"grid file '{path}': unknown extension '{ext}'; allowed: .vol "
                            "or .npy")


def world_box(header: GridHeader) -> tuple:
    """``(lo, hi, rotated)``: the axis-aligned world box of a grid's voxel cells (a
    ``.vol`` header's box, the unit cube for ``.npy``, the transformed box for ``.vdb``),
    and whether the file's transform rotates or shears (a ``.vol`` box cannot)."""
    if header.vdb_grid is None:
        lo, hi = header.bbox or ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
        return tuple(map(float, lo)), tuple(map(float, hi)), False
    from mitsuba_plugins.grids.gridheader import grid_to_world
    matrix = grid_to_world(header)
    corners = np.array([[a, b, c, 1.0] for a in (0, 1) for b in (0, 1) for c in (0, 1)])
    world = (matrix @ corners.T)[:3].T
    linear = matrix[:3, :3]
    rotated = bool(np.any(np.abs(linear - np.diag(np.diag(linear))) > 1e-9 * np.abs(linear).max()))
    return tuple(world.min(axis=0).tolist()), tuple(world.max(axis=0).tolist()), rotated


def convert(source, target, grid: str = "density", report=print) -> dict:
    """Write grid ``source`` (``.vol``, ``.npy`` or ``.vdb``) as ``target`` (``.vol``,
    ``.npy`` or ``.vdb``), slab by slab (one slab in memory), validating every value, to
    a temporary name renamed when complete. ``.vol`` and ``.npy`` are dense: ``report``
    is told the size before anything is written. A ``.vol`` keeps the world box (a
    ``.vdb``'s rotation cannot be kept: ``report`` says so); ``.npy`` keeps the values
    only; a ``.vdb`` keeps the placement (a ``.vdb``'s own transform, else voxel centres
    spread over the world box) and stores only the non-zero voxels, as grid ``grid``."""
    from mitsuba_plugins.output import atomic_path, check_targets
    check_targets([target], extensions=(".vol", ".npy", ".vdb"), option="OUT")
    header = read_header(source, grid)
    ext = os.path.splitext(os.fspath(target))[1].lower()
    z, y, x, c = header.shape
    size = 4 * header.size
    lo, hi, rotated = world_box(header)
    if ext == ".vdb":
        from mitsuba_plugins.grids.vdb_openvdb import write_vdb
        name = re.sub(r"\[\d+\]$", "", grid)    # an address name[k] writes grid 'name'
        _check_no_grid_lost(target, name)
        report(f"{target}: grid {name!r}, {x} x {y} x {z} x {c} voxels, zeros left inactive")
        with atomic_path(target) as tmp:
            write_vdb(tmp, name, header.shape, _index_to_world(header, lo, hi),
                      ((z0, _checked(header, slab)) for z0, slab in iter_slabs(header)))
        return {"shape": header.shape, "bytes": None, "bbox": (lo, hi), "rotated": False}
    report(f"{target}: {x} x {y} x {z} x {c} float32 values, {size / 2 ** 20:.4g} MiB (dense)")
    if rotated and ext == ".vol":
        report(f"{target}: note: the file's transform rotates or shears the grid; a .vol "
               "keeps its axis-aligned world box only (place it with to_world)")
    with atomic_path(target) as tmp, open(tmp, "wb") as f:
        if ext == ".vol":
            f.write(VOL_HEADER.pack(VOL_MAGIC, VOL_VERSION, VOL_ENCODING_FLOAT32, x, y, z, c,
                                    *lo, *hi))
        else:
            np.lib.format.write_array_header_1_0(
                f, {"descr": "<f4", "fortran_order": False, "shape": header.shape})
        for _, slab in iter_slabs(header):
            check_values(header.path, "data", slab)
            f.write(np.ascontiguousarray(slab, dtype="<f4").tobytes())
    return {"shape": header.shape, "bytes": size, "bbox": (lo, hi), "rotated": rotated}


def _check_no_grid_lost(target, name: str) -> None:
    """Refuse to replace an existing ``.vdb`` that holds a grid other than the one grid
    ``name`` the output holds (``grid convert f.vdb f.vdb`` dropped every other grid of
    the file without a word: issue 46)."""
    from mitsuba_plugins.grids.vdb_openvdb import grid_list
    if not os.path.isfile(target):
        return
    try:
        held = [e.address for e in grid_list(target)]
    except GridFileError:
        return                  # not an OpenVDB file: no grid to lose
    lost = [a for a in held if a != name]
    if lost:
        raise GridFileError(
            f"OUT '{os.fspath(target)}' holds the grid(s) {', '.join(map(repr, held))}; the "
            f"output holds grid {name!r} alone, so the others would be lost; write to "
            "another file (grids are never dropped)")


def _checked(header: GridHeader, slab: np.ndarray) -> np.ndarray:
    check_values(header.path, "data", slab)
    return slab


def _index_to_world(header: GridHeader, lo, hi) -> np.ndarray:
    """4x4 map from index (i, j, k) of the loaded box (voxel centres) to world."""
    if header.index_to_world is not None:
        matrix = np.array(header.index_to_world, dtype=np.float64)
        offset = np.eye(4)
        offset[:3, 3] = header.index_min
        return matrix @ offset
    z, y, x, _ = header.shape
    h = (np.array(hi, np.float64) - lo) / (x, y, z)
    matrix = np.diag([*h, 1.0])
    matrix[:3, 3] = np.array(lo, np.float64) + 0.5 * h
    return matrix
