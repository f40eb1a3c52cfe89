"""What every grid-file reader shares: the error type, the header record, shape and value
checks. Kept apart so that the format readers (:mod:`mitsuba_plugins.grids.gridio` for ``.vol``
/ ``.npy``, :mod:`mitsuba_plugins.grids.vdb_openvdb` for ``.vdb``) import it, not each other."""
from __future__ import annotations

import dataclasses
import errno
import os
import stat

import numpy as np

#: channel counts a density / albedo / emission grid may have
GRID_CHANNELS = (1, 3)
#: smallest resolution per axis (trilinear interpolation needs two samples)
MIN_RESOLUTION = 2
#: most values a dense grid may hold: Dr.Jit arrays are indexed with 32 bits
MAX_VALUES = 2 ** 32 - 1


class GridFileError(ValueError):
    """A grid file is missing, malformed or holds invalid values."""


@dataclasses.dataclass(frozen=True)
class GridHeader:
    """Shape and placement of a grid file, read without loading its data."""
    path: str
    shape: tuple  # (Z, Y, X, C)
    bbox: tuple | None  # ((xmin, ymin, zmin), (xmax, ymax, zmax)); None for .npy
    offset: int  # byte offset of the data
    dtype: np.dtype  # on-disk element type
    fortran_order: bool = False
    vdb_grid: str | None = None  # .vdb: the grid read (mitsuba_plugins.grids.vdb_openvdb)
    index_min: tuple | None = None  # .vdb: index of the box's first voxel
    index_to_world: tuple | None = None  # .vdb: the file's 4x4 index -> world matrix

    @property
    def resolution(self) -> tuple:
        """(X, Y, Z), Mitsuba's order."""
        z, y, x, _ = self.shape
        return (x, y, z)

    @property
    def channels(self) -> int:
        return self.shape[3]

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))


def fail(path, what: str):
    raise GridFileError(f"grid file '{path}': {what}")


def check_shape(path, shape, dense: bool = True):
    z, y, x, c = shape
    if c not in GRID_CHANNELS:
        fail(path, f"{c} channels; allowed: {' or '.join(map(str, GRID_CHANNELS))}")
    if min(x, y, z) < MIN_RESOLUTION:
        fail(path, f"resolution {x} x {y} x {z} (X x Y x Z); each axis needs at least "
                    f"{MIN_RESOLUTION} cells")
    if dense:
        check_dense_size(path, shape)


def check_dense_size(path, shape) -> None:
    """Refuse a box too large to be held or read densely (2^32 values: Dr.Jit's array
    index); a ``.vdb`` read into sparse bricks is checked by its bricks instead."""
    z, y, x, c = shape
    values = x * y * z * c
    if values > MAX_VALUES:
        hint = ("; grid_medium's storage = 'sparse' holds only its bricks"
                if os.fspath(path).lower().endswith(".vdb") else "")
        fail(path, f"{x} x {y} x {z} x {c} = {values:.4g} values; a dense grid holds at most "
                    f"2^32 - 1 = {MAX_VALUES:.4g} (Dr.Jit's array index is 32 bits){hint}")


def check_regular_file(path) -> None:
    """Raise :class:`GridFileError` unless ``path`` is a readable regular file, saying
    what it is instead (missing, a folder, a symbolic-link loop, a FIFO or device:
    opening a FIFO would block forever)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        target = os.path.islink(path) and os.readlink(path)
        fail(path, f"a symbolic link to '{target}', which does not exist" if target
              else "file does not exist")
    except OSError as error:
        if error.errno == errno.ELOOP:
            fail(path, "a symbolic link loop")
        fail(path, f"cannot be read ({error.strerror})")
    if stat.S_ISDIR(st.st_mode):
        fail(path, "is a folder, not a grid file")
    if not stat.S_ISREG(st.st_mode):
        kind = "a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode) else \
            "a socket" if stat.S_ISSOCK(st.st_mode) else "a device"
        fail(path, f"is {kind}, not a regular file")
    if not os.access(path, os.R_OK):
        fail(path, "is not readable (permission denied)")


def check_values(path, name: str, values: np.ndarray, lo: float = 0.0,
                 hi: float | None = None) -> None:
    """Raise unless every value is finite and within [lo, hi] (an empty array passes:
    a brick row or slab without stored values)."""
    if values.size == 0:
        return
    bad = ~np.isfinite(values)
    if bad.any():
        fail(path, f"{name}: {int(bad.sum())} non-finite value(s) (NaN or Inf)")
    vmin = float(values.min())
    if vmin < lo:
        fail(path, f"{name}: negative value {vmin:g}; allowed: >= {lo:g}")
    if hi is not None:
        vmax = float(values.max())
        if vmax > hi:
            fail(path, f"{name}: value {vmax:g} above {hi:g}; allowed: [{lo:g}, {hi:g}]")


def grid_to_world(header) -> np.ndarray:
    """4x4 map from the loaded box's unit cube (voxel ``x``'s centre at
    ``(x + 1/2) / N``) to world space through the file's index-to-world transform."""
    z, y, x, _ = header.shape
    matrix = np.array(header.index_to_world, dtype=np.float64)
    unit_to_index = np.diag([x, y, z, 1.0])
    unit_to_index[:3, 3] = np.array(header.index_min, dtype=np.float64) - 0.5
    return matrix @ unit_to_index

