"""OpenVDB input (``.vdb``), read through OpenVDB's own library.

OpenVDB's Python module is Debian's ``python3-openvdb`` (OpenVDB 10, module
``pyopenvdb``): it is not on PyPI and is built against Debian's Python and numpy 1.x,
so in an environment with numpy 2 (or another Python build) it cannot be imported. The
file is therefore read by a worker process (:mod:`mitsuba_plugins._vdb_worker`) run with
the Python that has the module (``/usr/bin/python3``, or ``MITSUBA_PLUGINS_VDB_PYTHON``),
which streams the grid's values back through a pipe, slab by slab. The package's own
environment needs no pin, and ``.vol`` / ``.npy`` never touch OpenVDB. Chose this over
pinning numpy < 2 in the venv because the pin would bind every user of the package to
Debian's numpy ABI, and would still fail with a Python other than Debian's 3.11.

Placement follows OpenVDB: voxel ``(i, j, k)``'s value sits at the file's index-to-world
transform applied to ``(i, j, k)``, values are interpolated between voxel centres, and
outside the active voxels and tiles the value is the grid's background, which must be 0.
The loaded box is the active index box grown by one voxel of background on every side,
so trilinear lookups fall to 0 across the border exactly as OpenVDB's do.
"""
from __future__ import annotations

import contextlib
import functools
import json
import os
import subprocess
from pathlib import Path

import numpy as np

WORKER = Path(__file__).with_name("_vdb_worker.py")
#: where OpenVDB's Python module is looked for (the variable, if set, alone)
PYTHON_VARIABLE = "MITSUBA_PLUGINS_VDB_PYTHON"
DEFAULT_PYTHON = "/usr/bin/python3"
INSTALL_HINT = "apt-get install -y python3-openvdb"
#: value types accepted for a density grid, and their channel counts
CHANNELS = {"float": 1, "half": 1, "vec3s": 3}
#: voxels of background around the active box (trilinear falls to 0 across it)
PAD = 1


def _fail(path, what: str):
    from mitsuba_plugins.gridio import GridFileError
    raise GridFileError(f"grid file '{path}': {what}")


@functools.lru_cache(maxsize=None)
def _python(candidates: tuple) -> str | None:
    for exe in candidates:
        if exe and os.access(exe, os.X_OK):
            probe = subprocess.run([exe, "-c", "import pyopenvdb"], capture_output=True)
            if probe.returncode == 0:
                return exe
    return None


def openvdb_python(path="") -> str:
    """The Python executable that can import OpenVDB's module; an error naming the apt
    package when there is none."""
    env = os.environ.get(PYTHON_VARIABLE)
    candidates = (env,) if env else (DEFAULT_PYTHON,)
    exe = _python(candidates)
    if exe is None:
        _fail(path, f"reading .vdb needs OpenVDB's Python module (pyopenvdb), which "
                    f"{' / '.join(c for c in candidates if c)} cannot import: {INSTALL_HINT} "
                    "(.vol and .npy grids need nothing)")
    return exe


def _run(path, *args) -> subprocess.CompletedProcess:
    proc = subprocess.run([openvdb_python(path), str(WORKER), *map(str, args)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        reason = (proc.stderr.strip().splitlines() or ["no message"])[-1]
        _fail(path, f"not a readable OpenVDB file ({reason})")
    return proc


def vdb_info(path, value_range: bool = True) -> list:
    """Every grid of ``path``: a list of dicts (see :mod:`mitsuba_plugins._vdb_worker`);
    without ``value_range`` their ``min``/``max`` are None (reading them costs a pass
    over every value)."""
    args = ["info", os.fspath(path)] + ([] if value_range else ["norange"])
    return json.loads(_run(path, *args).stdout)


def read_vdb_header(path, grid: str):
    """A :class:`~mitsuba_plugins.gridio.GridHeader` for grid ``grid`` of ``path``: its
    active box grown by :data:`PAD` voxels, refusing what cannot be placed or stored."""
    from mitsuba_plugins.gridio import GridHeader, _check_shape
    grids = vdb_info(path, value_range=False)
    found = [g for g in grids if g["name"] == grid]
    if not found:
        names = ", ".join(repr(g["name"]) for g in grids) or "none"
        _fail(path, f"no grid named {grid!r}; the file holds: {names}")
    g = found[0]
    if g["type"] not in CHANNELS:
        _fail(path, f"grid {grid!r} holds {g['type']} values; allowed: "
                    f"{', '.join(CHANNELS)}")
    background = np.asarray(g["background"], dtype=np.float64)
    if np.any(background != 0):
        _fail(path, f"grid {grid!r} has background {g['background']}; allowed: 0 (a "
                    "non-zero background would fill all space)")
    if not g["linear"]:
        _fail(path, f"grid {grid!r} has a {g['transform_type']} transform; allowed: an "
                    "affine (linear) transform, not a frustum")
    matrix = np.array(g["index_to_world"], dtype=np.float64)
    det = np.linalg.det(matrix[:3, :3])
    if not (np.all(np.isfinite(matrix)) and abs(det) > 1e-30):
        _fail(path, f"grid {grid!r} has a singular index-to-world transform")
    lo = np.array(g["index_min"] if g["index_min"] is not None else [0, 0, 0])
    hi = np.array(g["index_max"] if g["index_max"] is not None else [0, 0, 0])
    nx, ny, nz = (hi - lo + 1 + 2 * PAD).tolist()
    shape = (nz, ny, nx, CHANNELS[g["type"]])
    _check_shape(path, shape)
    return GridHeader(os.fspath(path), shape, None, 0, np.dtype("<f4"), vdb_grid=grid,
                      index_min=tuple((lo - PAD).tolist()),
                      index_to_world=tuple(map(tuple, matrix.tolist())))


@contextlib.contextmanager
def _reader(header, command: str, *args):
    """Run the worker's ``command`` on the header's grid and box; yields ``read(count)``,
    which returns exactly ``count`` bytes of its output or fails naming the file (with
    the worker's last line). The worker is killed if the caller stops early."""
    z, y, x, _ = header.shape
    i0, j0, k0 = header.index_min
    argv = [command, header.path, header.vdb_grid, i0, j0, k0, x, y, z, *args]
    with subprocess.Popen([openvdb_python(header.path), str(WORKER), *map(str, argv)],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE) as proc:
        def read(count: int) -> bytes:
            raw = proc.stdout.read(count)
            if len(raw) != count:
                proc.wait()
                reason = proc.stderr.read().decode(errors="replace").strip()
                _fail(header.path, "reading grid values failed ("
                      + (reason.splitlines()[-1] if reason else "stream ended early") + ")")
            return raw
        try:
            yield read
        finally:
            if proc.poll() is None:
                proc.kill()


def iter_vdb_slabs(header, slab_bytes: int):
    """Yield ``(z0, slab)``: float32 ``(k, Y, X, C)`` slabs of the header's box, read by
    the worker and streamed through a pipe (one slab in memory at a time)."""
    z, y, x, c = header.shape
    per_slab = max(1, slab_bytes // (4 * x * y * c))
    with _reader(header, "read", per_slab) as read:
        for z0 in range(0, z, per_slab):
            k = min(per_slab, z - z0)
            raw = read(4 * k * y * x * c)
            yield z0, np.frombuffer(raw, dtype="<f4").reshape(k, y, x, c)


def iter_vdb_bricks(header):
    """Yield ``(row, (by, bx), blocks)``: the stored bricks of each brick row of the
    header's box (:mod:`mitsuba_plugins.bricks`), cut by the worker, which never holds
    more than one row of the box; only stored bricks cross the pipe."""
    from mitsuba_plugins.bricks import BRICK, SIDE
    z, _, _, c = header.shape
    with _reader(header, "bricks") as read:
        for expected in range(-(-z // BRICK)):
            row, n = np.frombuffer(read(8), dtype="<i4")
            if row != expected or n < 0:
                _fail(header.path, f"reading grid values failed (row {row}, expected "
                                   f"{expected})")
            cols = np.frombuffer(read(8 * n), dtype="<i4").reshape(2, n).astype(np.intp)
            blocks = np.frombuffer(read(4 * n * SIDE ** 3 * c), dtype="<f4")
            yield int(row), (cols[0], cols[1]), blocks.reshape(n, SIDE, SIDE, SIDE, c)


def write_vdb(path, name: str, shape, index_to_world: np.ndarray, slabs) -> None:
    """Write a one-grid ``.vdb`` at ``path`` through the worker: ``slabs`` yields
    ``(z0, (k, Y, X, C) float32)`` in order; voxel (i, j, k) sits at ``index_to_world``
    (4x4, column vectors) applied to (i, j, k)."""
    z, y, x, c = shape
    rows = np.asarray(index_to_world, dtype=np.float64)[:3].ravel().tolist()
    args = ["write", os.fspath(path), name, x, y, z, c, *rows]
    with subprocess.Popen([openvdb_python(path), str(WORKER), *map(str, args)],
                          stdin=subprocess.PIPE, stderr=subprocess.PIPE) as proc:
        try:
            for _, slab in slabs:
                proc.stdin.write(np.ascontiguousarray(slab, dtype="<f4").tobytes())
            proc.stdin.close()
        except BrokenPipeError:
            pass
        if proc.wait() != 0:
            reason = proc.stderr.read().decode(errors="replace").strip()
            _fail(path, "writing failed (" + (reason.splitlines()[-1] if reason else
                                              "no message") + ")")


def grid_to_world(header) -> np.ndarray:
    """4x4 map from the loaded box's unit cube (voxel ``x``'s centre at
    ``(x + 1/2) / N``) to world space through the file's index-to-world transform."""
    z, y, x, _ = header.shape
    matrix = np.array(header.index_to_world, dtype=np.float64)
    unit_to_index = np.diag([x, y, z, 1.0])
    unit_to_index[:3, 3] = np.array(header.index_min, dtype=np.float64) - 0.5
    return matrix @ unit_to_index

