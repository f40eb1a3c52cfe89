"""OpenVDB input (``.vdb``), read through OpenVDB's own library.

OpenVDB's Python module is Debian's ``python3-openvdb`` (OpenVDB 10, module
``pyopenvdb``): it is not on PyPI and is built against Debian's Python and numpy 1.x,
so in an environment with numpy 2 (or another Python build) it cannot be imported. The
file is therefore read by a worker process (:mod:`mitsuba_plugins.grids._vdb_worker`) run with
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
import select
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from mitsuba_plugins.grids.gridheader import GridHeader, check_shape, fail as _fail

WORKER = Path(__file__).with_name("_vdb_worker.py")
#: where OpenVDB's Python module is looked for (the variable, if set, alone)
PYTHON_VARIABLE = "MITSUBA_PLUGINS_VDB_PYTHON"
DEFAULT_PYTHON = "/usr/bin/python3"
INSTALL_HINT = "apt-get install -y python3-openvdb"
#: value types accepted for a density grid, and their channel counts
CHANNELS = {"float": 1, "half": 1, "vec3s": 3}
#: voxels of background around the active box (trilinear falls to 0 across it)
PAD = 1





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


#: environment variables of the reader's limits
MEMORY_VARIABLE = "MITSUBA_PLUGINS_VDB_MEMORY"
TIMEOUT_VARIABLE = "MITSUBA_PLUGINS_VDB_TIMEOUT"
#: the reader's data segment may grow to the larger of this and FILE_FACTOR x the file
#: size (OpenVDB trees of compressed or half-float files are several times the file)
MIN_MEMORY = 4 << 30
FILE_FACTOR = 32
#: seconds the reader may go without sending anything before it is stopped
DEFAULT_TIMEOUT = 300.0
#: index coordinates a loaded box may span: OpenVDB 10's copyToArray crashes (or spins)
#: on boxes reaching past +-2^30 (measured: a box ending at 2^30 + 2 segfaults)
INDEX_LIMIT = 1 << 30
#: value types a density (or emission) grid may hold
ALLOWED_TYPES = tuple(CHANNELS)


def _limits(path) -> tuple:
    """``(environment, timeout)`` of a reader of ``path``."""
    env = dict(os.environ)
    env["MITSUBA_PLUGINS_VDB_PARENT"] = str(os.getpid())
    try:
        size = os.path.getsize(path)
    except OSError:
        size = 0
    env["MITSUBA_PLUGINS_VDB_MEMORY"] = os.environ.get(MEMORY_VARIABLE) or \
        str(max(MIN_MEMORY, FILE_FACTOR * size))
    timeout = float(os.environ.get(TIMEOUT_VARIABLE) or DEFAULT_TIMEOUT)
    return env, timeout


class _Worker:
    """One run of the worker: data from its own pipe, read with a deadline; its messages
    in a temporary file (a full stderr pipe cannot block it)."""

    def __init__(self, path, argv, stdin=None):
        self.path = path
        env, self.timeout = _limits(path)
        self.errors = tempfile.TemporaryFile()
        self.proc = subprocess.Popen([openvdb_python(path), str(WORKER), *map(str, argv)],
                                     stdin=stdin, stdout=subprocess.PIPE, stderr=self.errors,
                                     env=env)

    def reason(self, default: str) -> str:
        """The worker's last line, once it has ended."""
        self.errors.seek(0)
        text = self.errors.read().decode(errors="replace").strip()
        return text.splitlines()[-1] if text else default

    def read(self, count: int) -> bytes:
        """Exactly ``count`` bytes of data; fails naming the file otherwise."""
        fd, data = self.proc.stdout.fileno(), bytearray()
        while len(data) < count:
            ready, _, _ = select.select([fd], [], [], self.timeout)
            if not ready:
                self.close()
                _fail(self.path, f"the OpenVDB reader sent nothing for {self.timeout:g} s and "
                                 f"was stopped (set {TIMEOUT_VARIABLE} to wait longer)")
            chunk = os.read(fd, min(count - len(data), 1 << 22))
            if not chunk:
                break
            data += chunk
        if len(data) != count:
            self.proc.wait()
            _fail(self.path, "reading grid values failed (" + self.reason(
                "the OpenVDB reader ended early" + self._signal()) + ")")
        return bytes(data)

    def _signal(self) -> str:
        code = self.proc.returncode
        return f", killed by signal {-code}" if code is not None and code < 0 else ""

    def read_line(self) -> bytes:
        """All the data up to the worker's exit (a JSON line)."""
        data = bytearray()
        fd = self.proc.stdout.fileno()
        while True:
            ready, _, _ = select.select([fd], [], [], self.timeout)
            if not ready:
                self.close()
                _fail(self.path, f"the OpenVDB reader sent nothing for {self.timeout:g} s and "
                                 f"was stopped (set {TIMEOUT_VARIABLE} to wait longer)")
            chunk = os.read(fd, 1 << 16)
            if not chunk:
                break
            data += chunk
        if self.proc.wait() != 0:
            _fail(self.path, "not a readable OpenVDB file (" + self.reason(
                "no message" + self._signal()) + ")")
        return bytes(data)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        self.proc.stdout.close()
        self.errors.close()


def grid_list(path) -> list:
    """The grids of ``path`` as :class:`~mitsuba_plugins.grids.vdb_header.GridEntry` (read from the
    header, without OpenVDB)."""
    from mitsuba_plugins.grids.gridheader import check_regular_file
    from mitsuba_plugins.grids.vdb_header import VdbHeaderError, read_grid_list
    check_regular_file(path)       # a FIFO would block the header read forever
    if leaf_reader() is None:
        openvdb_python(path)       # reading a .vdb needs it: say so first
    try:
        return read_grid_list(path)
    except VdbHeaderError as error:
        _fail(path, f"not a readable OpenVDB file ({error})")


def _unsupported(entry) -> str | None:
    """Why a grid cannot be read here (None if it can)."""
    if entry.value_type in ALLOWED_TYPES:
        return None
    return f"holds {entry.value_type} values; allowed: {', '.join(ALLOWED_TYPES)}"


def vdb_info(path, value_range: bool = True, addresses=None) -> list:
    """Grids of ``path`` (every one, or those ``addresses`` name), in file order: dicts
    with ``name``, ``address`` (the name, or ``name[k]`` when several grids share it),
    ``type``, and, for grids of a readable type, what :mod:`mitsuba_plugins.grids._vdb_worker`
    reports (``readable`` true); a grid of another type has ``readable`` false and
    ``reason``. Without ``value_range`` ``min``/``max`` are None (reading them costs a
    pass over every value)."""
    entries = grid_list(path)
    if addresses is not None:
        entries = [e for e in entries if e.address in addresses]
    readable = [e.address for e in entries if _unsupported(e) is None]
    details = {}
    if readable:
        worker = _Worker(path, ["info", os.fspath(path), *readable]
                         + ([] if value_range else ["norange"]))
        try:
            details = {g["address"]: g for g in json.loads(worker.read_line())}
        finally:
            worker.close()
    out = []
    for e in entries:
        base = {"name": e.name, "address": e.address, "type": e.value_type}
        if e.address in details:
            out.append({**details[e.address], **base, "readable": True})
        else:
            out.append({**base, "readable": False, "reason": _unsupported(e),
                        "active_voxels": None, "index_min": None, "index_max": None,
                        "min": None, "max": None})
    return out


def read_vdb_header(path, grid: str):
    """A :class:`~mitsuba_plugins.grids.gridheader.GridHeader` for the grid ``grid`` addresses in
    ``path`` (a unique name or ``name[k]``): its active box grown by :data:`PAD` voxels,
    refusing what cannot be placed or stored."""
    from mitsuba_plugins.grids.vdb_header import select as select_grid
    try:
        entry = select_grid(grid_list(path), grid)
    except LookupError as error:
        _fail(path, str(error))
    reason = _unsupported(entry)
    if reason:
        _fail(path, f"grid {entry.address!r} {reason}")
    reader = leaf_reader()
    if reader is None:
        g = vdb_info(path, value_range=False, addresses=[entry.address])[0]
    else:      # in this process; OpenVDB's grid stays loaded for iter_vdb_bricks
        g = _in_process(path, entry.address, reader.info, os.fspath(path), entry.address)
    grid = entry.address
    if "level" in str(g.get("class", "")).lower():
        _fail(path, f"grid {grid!r} is a level set; allowed: a fog volume (a level set is a "
                    "surface: convert it to a fog volume, e.g. OpenVDB's sdfToFogVolume)")
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
    if np.any(lo - PAD < -INDEX_LIMIT) or np.any(hi + PAD > INDEX_LIMIT - 1):
        _fail(path, f"grid {grid!r} has active voxels at index {lo.tolist()} - {hi.tolist()}; "
                    f"allowed: indices in [-2^30 + {PAD}, 2^30 - {PAD + 1}] (OpenVDB's "
                    "reader fails beyond)")
    nx, ny, nz = (hi - lo + 1 + 2 * PAD).tolist()
    shape = (nz, ny, nx, CHANNELS[g["type"]])
    check_shape(path, shape, dense=False)     # dense reads check the size (iter_slabs)
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
    worker = _Worker(header.path, [command, header.path, header.vdb_grid, i0, j0, k0, x, y,
                                   z, *args])
    try:
        yield worker.read
    finally:
        worker.close()


def iter_vdb_slabs(header, slab_bytes: int):
    """Yield ``(z0, slab)``: float32 ``(k, Y, X, C)`` slabs of the header's box, read by
    the worker and streamed through a pipe (one slab in memory at a time)."""
    reader = leaf_reader()
    if reader is not None:
        reader.release()     # the grid its info() kept: the worker reads the slabs
    z, y, x, c = header.shape
    per_slab = max(1, slab_bytes // (4 * x * y * c))
    with _reader(header, "read", per_slab) as read:
        for z0 in range(0, z, per_slab):
            k = min(per_slab, z - z0)
            raw = read(4 * k * y * x * c)
            yield z0, np.frombuffer(raw, dtype="<f4").reshape(k, y, x, c)


#: which reader cuts bricks: "auto" (the compiled one where it was built, else the
#: worker), "extension" (fails if it was not built) or "worker"
READER_VARIABLE = "MITSUBA_PLUGINS_VDB_READER"


def leaf_reader():
    """The compiled leaf-level reader (``mitsuba_plugins.grids._openvdb_bricks``, built at install
    where Debian's libopenvdb-dev is present), or None where it is absent or
    ``$MITSUBA_PLUGINS_VDB_READER`` is ``worker``."""
    choice = os.environ.get(READER_VARIABLE, "auto")
    if choice not in ("auto", "extension", "worker"):
        raise ValueError(f"${READER_VARIABLE} = {choice!r}; allowed: auto, extension, worker")
    if choice == "worker":
        return None
    try:
        from mitsuba_plugins.grids import _openvdb_bricks
    except ImportError as error:
        if choice == "extension":
            raise ImportError(
                f"${READER_VARIABLE}=extension, but mitsuba_plugins.grids._openvdb_bricks is not "
                f"built ({error}): apt-get install -y libopenvdb-dev libboost-dev g++, then "
                "reinstall the package") from error
        return None
    return _openvdb_bricks


def iter_vdb_bricks(header):
    """Yield ``(row, (by, bx), blocks)``: the stored bricks of each brick row of the
    header's box (:mod:`mitsuba_plugins.grids.bricks`). Cut by the compiled leaf-level reader
    (:func:`leaf_reader`) from OpenVDB's leaf nodes and tiles where it is built, else by
    the worker in tiles (it never holds a whole row of the box; only stored bricks cross
    the pipe). Both give the same bricks (tests/grids/test_vdb_reader.py)."""
    reader = leaf_reader()
    if reader is not None:
        yield from _leaf_bricks(reader, header)
        return
    from mitsuba_plugins.grids.bricks import BRICK, SIDE
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


def _in_process(path, grid: str, call, *args):
    """``call(*args)`` of the compiled reader on ``grid`` of ``path``; its failures (OpenVDB's
    IoError, bad_alloc, ...) become one line naming the file."""
    try:
        return call(*args)
    except MemoryError:
        _fail(path, f"out of memory reading grid {grid!r}")
    except Exception as error:
        _fail(path, f"reading grid {grid!r} failed ({error})")


def _leaf_bricks(reader, header):
    from mitsuba_plugins.grids.bricks import BRICK
    z, y, x, c = header.shape
    i0, j0, k0 = header.index_min
    coords, blocks = _in_process(header.path, header.vdb_grid, reader.bricks,
                                 os.fspath(header.path), header.vdb_grid, i0, j0, k0, x, y, z)
    if c == 1:
        blocks = blocks[..., None]
    ends = np.searchsorted(coords[:, 0], np.arange(-(-z // BRICK) + 1), side="left")
    for row in range(ends.size - 1):
        rows = slice(ends[row], ends[row + 1])
        cols = coords[rows, 1:].astype(np.intp)
        yield row, (cols[:, 0], cols[:, 1]), blocks[rows]


def write_vdb(path, name: str, shape, index_to_world: np.ndarray, slabs) -> None:
    """Write a one-grid ``.vdb`` at ``path`` through the worker: ``slabs`` yields
    ``(z0, (k, Y, X, C) float32)`` in order; voxel (i, j, k) sits at ``index_to_world``
    (4x4, column vectors) applied to (i, j, k)."""
    z, y, x, c = shape
    rows = np.asarray(index_to_world, dtype=np.float64)[:3].ravel().tolist()
    worker = _Worker(path, ["write", os.fspath(path), name, x, y, z, c, *rows],
                     stdin=subprocess.PIPE)
    try:
        try:
            for _, slab in slabs:
                worker.proc.stdin.write(np.ascontiguousarray(slab, dtype="<f4").tobytes())
            worker.proc.stdin.close()
        except BrokenPipeError:
            pass
        if worker.proc.wait() != 0:
            _fail(path, "writing failed (" + worker.reason("no message") + ")")
    finally:
        worker.close()

