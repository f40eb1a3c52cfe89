"""Checks of a grid's values as they load and when they are edited: finite and in range
(tiny negatives of simulation noise set to 0, :class:`ValueCheck`), edits refused with
the previous values put back (:func:`checked_edit`), and dense storage within the
machine's memory (:func:`check_dense_memory`)."""
from __future__ import annotations

import os

import numpy as np

from mitsuba_plugins.grids import gridio
from mitsuba_plugins.params import PluginParameterError, floats


def checked_edit(name: str, values: np.ndarray, restore, lo: float = 0.0) -> np.ndarray:
    """``values`` of an edited grid parameter ``name``, every one finite and >= ``lo``;
    where one is not, ``restore()`` puts the previous values back (``params`` then holds
    what renders) and the error names the parameter and the allowed range."""
    bad = int(np.count_nonzero(~np.isfinite(values)))
    low = int(np.count_nonzero(values < lo)) if not bad else 0
    if not (bad or low):
        return values
    restore()
    what = f"{bad} non-finite value(s) (NaN or Inf)" if bad else \
        f"{low} value(s) below {lo:g} (smallest {float(values.min()):g})"
    raise PluginParameterError(
        f"grid_medium: parameter '{name}' holds {what}; allowed: finite values >= {lo:g}. "
        "The previous values are kept (in params too)")


# -- loading a grid file ------------------------------------------------------------------
#: negative values down to -TINY_NEGATIVE are taken as float noise of simulation output
#: (one voxel of -1e-6 made a grid unusable): set to 0, with one warning per grid that
#: says how many; more negative values are refused
TINY_NEGATIVE = 1e-4


class ValueCheck:
    """Checks the values of one grid as they stream in (finite, >= ``lo``), setting
    tiny negatives to 0 where ``lo`` is 0; :meth:`report` warns once how many were."""

    def __init__(self, path, what: str, lo: float = 0.0):
        self.path, self.what, self.lo = path, what, lo
        self.clamped, self.smallest = 0, 0.0

    def __call__(self, values: np.ndarray) -> np.ndarray:
        if self.lo == 0.0 and values.size:
            tiny = (values < 0) & (values >= -TINY_NEGATIVE)
            n = int(np.count_nonzero(tiny))
            if n:
                self.clamped += n
                self.smallest = min(self.smallest, float(values[tiny].min()))
                values = np.where(tiny, np.float32(0), values)
        gridio.check_values(self.path, self.what, values, self.lo)
        return values

    def report(self) -> None:
        if self.clamped:
            import warnings
            warnings.warn(f"grid_medium: grid file '{self.path}': {self.what}: "
                          f"{self.clamped} value(s) in [-{TINY_NEGATIVE:g}, 0) (smallest "
                          f"{self.smallest:g}) set to 0", stacklevel=2)


#: largest share of this machine's memory that dense storage may take
DENSE_MEMORY_SHARE = 0.25


def machine_memory() -> int:
    """Bytes of physical memory of this machine (0 where unknown)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return 0


def check_dense_memory(header, stored) -> None:
    """Refuse dense storage that would take over :data:`DENSE_MEMORY_SHARE` of this
    machine's memory (two voxels of a .vdb spanning a 1203^3 box allocated ~7 GB without a
    word), saying the size and the fix."""
    nbytes = 4 * int(np.prod(stored))
    limit = DENSE_MEMORY_SHARE * machine_memory()
    if limit and nbytes > limit:
        z, y, x, c = stored
        raise PluginParameterError(
            f"grid_medium: storage = 'dense' would allocate {nbytes / 1e9:.3g} GB for the "
            f"{x} x {y} x {z} x {c} box of '{header.path}'; allowed: at most "
            f"{limit / 1e9:.3g} GB here ({DENSE_MEMORY_SHARE:g} of this machine's memory); use "
            "storage = 'sparse' (or 'auto'), which holds only the bricks with values")


def check_float32(name: str, value: float) -> float:
    """``value`` of parameter ``name`` where float32 holds it (refused: an overflow to inf)."""
    with np.errstate(over="ignore"):
        as_f32 = np.float32(value)
    if not np.isfinite(as_f32):
        raise PluginParameterError(
            f"grid_medium: parameter '{name}' = {value:g} is invalid; allowed: a finite "
            "number >= 0 that float32 holds (at most 3.4e38)")
    return value


def checked_factors(scale, factor, accepted: tuple) -> tuple:
    """The edited ``scale`` (an ``mi.Float``) and ``sigma_t`` factor (an ``mi.Color3f``)
    of a grid medium as Python floats, each finite and >= 0; a refused value is replaced
    by the last ``accepted`` one, so that params holds what renders (a NaN stayed in
    params while renders used the old value)."""
    import mitsuba as mi
    value = floats(scale)[0]
    if not (np.isfinite(value) and value >= 0):
        mi.set_property(scale, mi.Float(accepted[0]))
        raise PluginParameterError(
            f"grid_medium: parameter 'scale' = {value!r} is invalid; allowed: a finite "
            f"number >= 0 (the previous value {accepted[0]:g} is kept)")
    channels = floats(factor)
    if not all(np.isfinite(f) and f >= 0 for f in channels):
        mi.set_property(factor, mi.Color3f(accepted[1]))
        raise PluginParameterError(
            f"grid_medium: parameter 'sigma_t' = {channels} is invalid; allowed: finite "
            f"values >= 0 (the previous value {accepted[1]} is kept)")
    return value, channels
