"""Reads OpenVDB files for :mod:`mitsuba_plugins.vdb`; runs under the Python that has
OpenVDB's module (Debian's ``python3-openvdb``, built for Debian's own Python and numpy
1.x), never inside the package's environment. It imports only pyopenvdb, numpy and the
standard library.

``info FILE [norange]``: one JSON line describing every grid of FILE (name, value type,
class, background, active voxels, active index box, value range unless ``norange``,
index-to-world matrix, whether the transform is linear).

``read FILE GRID I0 J0 K0 NX NY NZ SLAB``: the values of GRID in the index box starting
at (I0, J0, K0) of NX x NY x NZ voxels (background outside the active voxels and tiles),
as raw little-endian float32 on stdout, SLAB k-slices at a time, each slab C-ordered
``(k, j, i, channel)``.

``write FILE GRID NX NY NZ C M00 .. M23``: a new file with one float (C = 1) or vec3s
(C = 3) grid GRID, index-to-world matrix rows M (3 x 4, column vectors), voxel (i, j, k)
of the box at index (i, j, k) plus the offset in the matrix' caller; values arrive on
stdin as raw little-endian float32 ``(k, j, i, channel)`` slices, one at a time; zeros
stay inactive background.

``bricks FILE GRID I0 J0 K0 NX NY NZ``: the same box cut into the stored bricks of
:mod:`mitsuba_plugins.bricks` here, so that only they cross the pipe: per brick row
(8 k-slices and the apron slice) the little-endian int32 pair (row, n), n int32 ``by``,
n int32 ``bx``, then n float32 blocks ``(SIDE, SIDE, SIDE, channel)``.
"""
import json
import sys


def _fail(message):
    sys.stderr.write(message.replace("\n", " ") + "\n")
    sys.exit(3)


def _open(path, name=None):
    import pyopenvdb as vdb
    try:
        if name is None:
            return vdb.readAll(path)[0]
        return vdb.read(path, name)
    except Exception as error:  # OpenVDB's IoError, KeyError, ...: one line for the caller
        _fail(f"{type(error).__name__}: {error}")


def _matrix(transform):
    """4x4 index -> world matrix (column vectors) of an affine transform."""
    origin = transform.indexToWorld((0, 0, 0))
    axes = [transform.indexToWorld(tuple(1 if a == b else 0 for b in range(3)))
            for a in range(3)]
    rows = [[axes[c][r] - origin[r] for c in range(3)] + [origin[r]] for r in range(3)]
    return rows + [[0.0, 0.0, 0.0, 1.0]]


def info(path, value_range=True):
    grids = []
    for grid in _open(path):
        lo, hi = grid.evalActiveVoxelBoundingBox()
        count = grid.activeVoxelCount()
        background = grid.background
        if not value_range:                 # evalMinMax reads every value (3 s at 3e8)
            vmin = vmax = None
        else:
            vmin, vmax = grid.evalMinMax() if count else (background, background)
        transform = grid.transform
        grids.append({
            "name": grid.name, "type": grid.valueTypeName,
            "class": str(grid.gridClass), "active_voxels": int(count),
            "background": list(background) if isinstance(background, tuple) else background,
            "index_min": list(lo) if count else None, "index_max": list(hi) if count else None,
            "min": list(vmin) if isinstance(vmin, tuple) else vmin,
            "max": list(vmax) if isinstance(vmax, tuple) else vmax,
            "transform_type": transform.typeName, "linear": bool(transform.isLinear),
            "index_to_world": _matrix(transform) if transform.isLinear else None,
            "half_float": bool(grid.saveFloatAsHalf),
        })
    sys.stdout.write(json.dumps(grids) + "\n")


def read(path, name, i0, j0, k0, nx, ny, nz, slab):
    import numpy as np
    grid = _open(path, name)
    channels = 3 if grid.valueTypeName.startswith("vec3") else 1
    out = sys.stdout.buffer
    for k in range(0, nz, slab):
        nk = min(slab, nz - k)
        shape = (nx, ny, nk, channels) if channels > 1 else (nx, ny, nk)
        block = np.zeros(shape, np.float32)
        grid.copyToArray(block, ijk=(i0, j0, k0 + k))
        block = block.reshape(nx, ny, nk, channels).transpose(2, 1, 0, 3)
        out.write(np.ascontiguousarray(block, dtype="<f4").tobytes())
    out.flush()


def write(path, name, nx, ny, nz, channels, *matrix):
    import numpy as np
    import pyopenvdb as vdb
    grid = vdb.Vec3SGrid() if channels == 3 else vdb.FloatGrid()
    grid.name = name
    rows = [list(matrix[4 * r:4 * r + 4]) for r in range(3)] + [[0.0, 0.0, 0.0, 1.0]]
    # OpenVDB's matrices act on row vectors: pass the transpose
    grid.transform = vdb.createLinearTransform([list(c) for c in zip(*rows)])
    inp = sys.stdin.buffer
    count = nx * ny * channels
    for k in range(nz):
        raw = inp.read(4 * count)
        if len(raw) != 4 * count:
            _fail(f"stream ended at slice {k} of {nz}")
        layer = np.frombuffer(raw, dtype="<f4").reshape(ny, nx, channels)
        block = layer.transpose(1, 0, 2)[:, :, None, :]
        block = np.ascontiguousarray(block if channels == 3 else block[..., 0])
        grid.copyFromArray(block, ijk=(0, 0, k), tolerance=0.0)
    vdb.write(path, grids=[grid])


def _bricks_module():
    """mitsuba_plugins/bricks.py, loaded by path (the package itself needs Dr.Jit)."""
    import importlib.util
    import os
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "bricks.py")
    spec = importlib.util.spec_from_file_location("_mitsuba_plugins_bricks", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def bricks(path, name, i0, j0, k0, nx, ny, nz):
    import struct
    import numpy as np
    b = _bricks_module()
    grid = _open(path, name)
    channels = 3 if grid.valueTypeName.startswith("vec3") else 1
    out = sys.stdout.buffer
    for row in range(-(-nz // b.BRICK)):
        first = row * b.BRICK
        k = min(first + b.SIDE, nz) - first
        shape = (nx, ny, k, channels) if channels > 1 else (nx, ny, k)
        block = np.zeros(shape, np.float32)
        grid.copyToArray(block, ijk=(i0, j0, k0 + first))
        layers = np.ascontiguousarray(block.reshape(nx, ny, k, channels).transpose(2, 1, 0, 3))
        (by, bx), blocks = b.cut_row(layers, (ny, nx, channels))
        out.write(struct.pack("<ii", row, by.size))
        out.write(by.astype("<i4").tobytes() + bx.astype("<i4").tobytes())
        out.write(np.ascontiguousarray(blocks, dtype="<f4").tobytes())
    out.flush()


if __name__ == "__main__":
    command, *args = sys.argv[1:]
    if command == "info":
        info(args[0], value_range=args[1:] != ["norange"])
    elif command == "read":
        read(args[0], args[1], *map(int, args[2:]))
    elif command == "write":
        write(args[0], args[1], *map(int, args[2:6]), *map(float, args[6:]))
    elif command == "bricks":
        bricks(args[0], args[1], *map(int, args[2:]))
    else:
        _fail(f"unknown command {command}")
