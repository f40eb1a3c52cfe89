"""Reads OpenVDB files for :mod:`mitsuba_plugins.grids.vdb_openvdb`; runs under the Python that has
OpenVDB's module (Debian's ``python3-openvdb``, built for Debian's own Python and numpy
1.x), never inside the package's environment. It imports only pyopenvdb, numpy, the
standard library and (by path) :mod:`mitsuba_plugins.grids.bricks`.

Data leave on their own channel: the descriptor that was standard output when the
worker started. Standard output itself is pointed at standard error first, so nothing
OpenVDB or Python prints can enter the data stream (a warning about two grids of one
name once did, and was read as voxel values). OpenVDB's log is set to errors only.

Limits (set by the parent through the environment): ``MITSUBA_PLUGINS_VDB_MEMORY`` caps
the worker's data segment in bytes (an allocation beyond it fails with one line), and
``MITSUBA_PLUGINS_VDB_PARENT`` names the parent's pid: the worker is killed when the
parent's thread that started it ends (Linux ``PR_SET_PDEATHSIG``), and exits at once if
the parent is already gone.

A grid is selected by its *address*: its name, or ``name[k]`` for the k-th of several
grids of one name (OpenVDB's own form, :mod:`mitsuba_plugins.grids.vdb_header`).

``info FILE ADDRESS... [norange]``: one JSON line describing each addressed grid (name,
value type, class, background, active voxels, active index box, value range unless
``norange``, index-to-world matrix, whether the transform is linear). Grids are read
one at a time.

``read FILE ADDRESS I0 J0 K0 NX NY NZ SLAB``: the values in the index box starting at
(I0, J0, K0) of NX x NY x NZ voxels (background outside the active voxels and tiles), as
raw little-endian float32, SLAB k-slices at a time, each slab C-ordered
``(k, j, i, channel)``; a slice larger than :data:`CHUNK_BYTES` is read in bands of j.

``bricks FILE ADDRESS I0 J0 K0 NX NY NZ``: the same box cut into the stored bricks of
:mod:`mitsuba_plugins.grids.bricks`, so that only they cross the pipe: per brick row (8
k-slices and the apron slice) the little-endian int32 pair (row, n), n int32 ``by``, n
int32 ``bx``, then n float32 blocks ``(SIDE, SIDE, SIDE, channel)``. Each row is read in
tiles of at most :data:`CHUNK_BYTES` (the bricks of a tile plus their apron), never as a
whole row of the box.

``write FILE GRID NX NY NZ C M00 .. M23``: a new file with one float (C = 1) or vec3s
(C = 3) grid GRID, index-to-world matrix rows M (3 x 4, column vectors), voxel (i, j, k)
of the box at index (i, j, k) plus the offset in the matrix' caller; values arrive on
stdin as raw little-endian float32 ``(k, j, i, channel)`` slices, one at a time; zeros
stay inactive background.
"""
import json
import os
import sys

#: most bytes of one copy out of the grid (a tile of a brick row, a band of a slice);
#: ``MITSUBA_PLUGINS_VDB_CHUNK`` overrides it (the tests cut tiny tiles with it)
CHUNK_BYTES = int(os.environ.get("MITSUBA_PLUGINS_VDB_CHUNK") or 1 << 26)
EXIT_FAILED = 3

# The data channel: the original standard output. Everything else printed goes to stderr.
DATA = os.fdopen(os.dup(1), "wb")
os.dup2(2, 1)
sys.stdout = sys.stderr


def _fail(message):
    sys.stderr.write(message.replace("\n", " ") + "\n")
    sys.stderr.flush()
    os._exit(EXIT_FAILED)


def _limit():
    """Die with the parent and stay within the memory the parent allows."""
    parent = os.environ.get("MITSUBA_PLUGINS_VDB_PARENT")
    if parent and sys.platform.startswith("linux"):
        import ctypes
        import signal
        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)   # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
        if os.getppid() != int(parent):
            os._exit(EXIT_FAILED)           # the parent is gone already
    memory = os.environ.get("MITSUBA_PLUGINS_VDB_MEMORY")
    if memory:
        import resource
        limit = int(memory)
        resource.setrlimit(resource.RLIMIT_DATA, (limit, limit))


def _limit_text():
    memory = os.environ.get("MITSUBA_PLUGINS_VDB_MEMORY")
    return (f" (limit {int(memory) >> 20} MiB; set MITSUBA_PLUGINS_VDB_MEMORY to allow more)"
            if memory else "")


def _vdb():
    try:
        import pyopenvdb as vdb
    except (MemoryError, SystemError) as error:  # a memory cap below what OpenVDB needs
        _fail(f"out of memory importing OpenVDB{_limit_text()} ({type(error).__name__})")
    vdb.setLoggingLevel("error")
    return vdb


def _open(path, address):
    vdb = _vdb()
    try:
        return vdb.read(path, address)
    except MemoryError:
        _fail(f"out of memory reading grid {address!r}{_limit_text()}")
    except Exception as error:  # OpenVDB's IoError, KeyError, ...: one line for the caller
        text = str(error)
        if "bad_alloc" in text:       # also what damaged sizes in a grid's data give
            _fail(f"out of memory reading grid {address!r}{_limit_text()}, or its data is "
                  "damaged (a corrupt or truncated file asks for a huge allocation)")
        _fail(f"{type(error).__name__}: {text}")


def _matrix(transform):
    """4x4 index -> world matrix (column vectors) of an affine transform."""
    origin = transform.indexToWorld((0, 0, 0))
    axes = [transform.indexToWorld(tuple(1 if a == b else 0 for b in range(3)))
            for a in range(3)]
    rows = [[axes[c][r] - origin[r] for c in range(3)] + [origin[r]] for r in range(3)]
    return rows + [[0.0, 0.0, 0.0, 1.0]]


def _listed(value):
    return list(value) if isinstance(value, tuple) else value


def info(path, addresses, value_range=True):
    grids = []
    for address in addresses:
        grid = _open(path, address)
        lo, hi = grid.evalActiveVoxelBoundingBox()
        count = grid.activeVoxelCount()
        background = grid.background
        if not value_range:                 # evalMinMax reads every value (3 s at 3e8)
            vmin = vmax = None
        else:
            vmin, vmax = grid.evalMinMax() if count else (background, background)
        transform = grid.transform
        grids.append({
            "name": grid.name, "address": address, "type": grid.valueTypeName,
            "class": str(grid.gridClass), "active_voxels": int(count),
            "background": _listed(background),
            "index_min": list(lo) if count else None, "index_max": list(hi) if count else None,
            "min": _listed(vmin), "max": _listed(vmax),
            "transform_type": transform.typeName, "linear": bool(transform.isLinear),
            "index_to_world": _matrix(transform) if transform.isLinear else None,
            "half_float": bool(grid.saveFloatAsHalf),
        })
        del grid
    DATA.write((json.dumps(grids) + "\n").encode())
    DATA.flush()


def _channels(grid):
    return 3 if grid.valueTypeName.startswith("vec3") else 1


def _copy(grid, ijk, nx, ny, nz, channels):
    """The index box at ``ijk`` of ``nx x ny x nz`` voxels as float32 ``(nz, ny, nx, C)``."""
    import numpy as np
    shape = (nx, ny, nz, channels) if channels > 1 else (nx, ny, nz)
    block = np.zeros(shape, np.float32)
    grid.copyToArray(block, ijk=ijk)
    return np.ascontiguousarray(block.reshape(nx, ny, nz, channels).transpose(2, 1, 0, 3))


def read(path, address, i0, j0, k0, nx, ny, nz, slab):
    grid = _open(path, address)
    c = _channels(grid)
    band = max(1, CHUNK_BYTES // (4 * nx * c))           # j-rows per copy of one slice
    for k in range(0, nz, slab):
        nk = min(slab, nz - k)
        if nk == 1 and band < ny:
            for j in range(0, ny, band):
                nj = min(band, ny - j)
                DATA.write(_copy(grid, (i0, j0 + j, k0 + k), nx, nj, 1, c).astype("<f4").tobytes())
        else:
            DATA.write(_copy(grid, (i0, j0, k0 + k), nx, ny, nk, c).astype("<f4").tobytes())
    DATA.flush()


def write(path, name, nx, ny, nz, channels, *matrix):
    import numpy as np
    vdb = _vdb()
    grid = vdb.Vec3SGrid() if channels == 3 else vdb.FloatGrid()
    grid.name = name
    rows = [list(matrix[4 * r:4 * r + 4]) for r in range(3)] + [[0.0, 0.0, 0.0, 1.0]]
    # OpenVDB's matrices act on row vectors: pass the transpose
    grid.transform = vdb.createLinearTransform([list(c) for c in zip(*rows)])
    # the tolerance is a value of the grid's type (a vec3s for Vec3SGrid)
    tolerance = (0.0, 0.0, 0.0) if channels == 3 else 0.0
    inp = sys.stdin.buffer
    count = nx * ny * channels
    for k in range(nz):
        raw = inp.read(4 * count)
        if len(raw) != 4 * count:
            _fail(f"stream ended at slice {k} of {nz}")
        layer = np.frombuffer(raw, dtype="<f4").reshape(ny, nx, channels)
        block = layer.transpose(1, 0, 2)[:, :, None, :]
        block = np.ascontiguousarray(block if channels == 3 else block[..., 0])
        grid.copyFromArray(block, ijk=(0, 0, k), tolerance=tolerance)
    vdb.write(path, grids=[grid])


def _bricks_module():
    """mitsuba_plugins/grids/bricks.py, loaded by path (the package itself needs Dr.Jit)."""
    import importlib.util
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "bricks.py")
    spec = importlib.util.spec_from_file_location("_mitsuba_plugins_bricks", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def bricks(path, address, i0, j0, k0, nx, ny, nz):
    import struct
    import numpy as np
    b = _bricks_module()
    grid = _open(path, address)
    c = _channels(grid)
    by_all, bx_all = -(-ny // b.BRICK), -(-nx // b.BRICK)
    # bricks per tile: (8 ty + 1) x (8 tx + 1) x SIDE x C floats within CHUNK_BYTES
    per_tile = max(1, CHUNK_BYTES // (4 * c * b.SIDE * b.SIDE * b.SIDE))
    tx = max(1, min(bx_all, int(per_tile ** 0.5)))
    ty = max(1, min(by_all, per_tile // tx))
    for row in range(-(-nz // b.BRICK)):
        first = row * b.BRICK
        k = min(first + b.SIDE, nz) - first
        rows, cols, blocks = [], [], []
        for y0 in range(0, by_all, ty):
            for x0 in range(0, bx_all, tx):
                ys, xs = y0 * b.BRICK, x0 * b.BRICK
                ny_t = min(min(y0 + ty, by_all) * b.BRICK + 1, ny) - ys    # + apron
                nx_t = min(min(x0 + tx, bx_all) * b.BRICK + 1, nx) - xs
                layers = _copy(grid, (i0 + xs, j0 + ys, k0 + first), nx_t, ny_t, k, c)
                (r, q), found = b.cut_row(layers, (ny_t, nx_t, c),
                                          bricks=(min(ty, by_all - y0), min(tx, bx_all - x0)))
                if r.size:
                    rows.append(r + y0)
                    cols.append(q + x0)
                    blocks.append(found)
        r = np.concatenate(rows) if rows else np.zeros(0, np.int64)
        q = np.concatenate(cols) if cols else np.zeros(0, np.int64)
        order = np.lexsort((q, r))          # row-major, as one piece would list them
        DATA.write(struct.pack("<ii", row, r.size))
        DATA.write(r[order].astype("<i4").tobytes() + q[order].astype("<i4").tobytes())
        if blocks:
            DATA.write(np.ascontiguousarray(np.concatenate(blocks)[order], dtype="<f4").tobytes())
    DATA.flush()


def main(argv):
    _limit()
    command, *args = argv
    try:
        if command == "info":
            norange = args[-1:] == ["norange"]
            info(args[0], args[1:-1] if norange else args[1:], value_range=not norange)
        elif command == "read":
            read(args[0], args[1], *map(int, args[2:]))
        elif command == "write":
            write(args[0], args[1], *map(int, args[2:6]), *map(float, args[6:]))
        elif command == "bricks":
            bricks(args[0], args[1], *map(int, args[2:]))
        else:
            _fail(f"unknown command {command}")
    except MemoryError:
        _fail(f"out of memory{_limit_text()}")
    except BrokenPipeError:
        os._exit(EXIT_FAILED)                # the parent stopped reading
    except Exception as error:
        text = str(error)
        _fail(f"out of memory{_limit_text()}" if "bad_alloc" in text else
              f"{type(error).__name__}: {text}")


if __name__ == "__main__":
    main(sys.argv[1:])
