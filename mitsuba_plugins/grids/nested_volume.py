"""A nested Mitsuba volume as a grid medium's store (``sigma_t`` without ``filename``):
its own lookups, majorants from its data when it has a grid, and what is read of any
volume by probing it (largest and smallest value, channels, range checks)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins.grids import gridio, placement
from mitsuba_plugins.grids.spectra import (GridValues, MODEL_CHANNELS, model_range,
                                           probe_wavelengths)
from mitsuba_plugins.grids.stores import Bounds, built_bounds, new_builder
from mitsuba_plugins.params import PluginParameterError


#: margin (local units) of majorant cells when a nested volume's transform is read
#: back from its printed 6-digit matrix
PARSED_TRANSFORM_MARGIN = 2e-3


#: relative slack on a constant volume's largest value read at sampled wavelengths
PROBE_SLACK = 1e-3


class VolumeStore:
    """A nested Mitsuba volume: its own lookups; majorants from its data when it has a
    grid (its transform read back from its printed matrix), else one cell."""
    kind = "volume"

    def __init__(self, volume: mi.Volume):
        self.volume = volume

    @classmethod
    def from_params(cls, p, file_only: tuple) -> "VolumeStore":
        """The nested ``sigma_t`` volume of ``grid_medium``'s parameters ``p`` (1 when not
        given); the parameters of a ``filename`` grid (``file_only``) are refused."""
        given = [name for name in file_only if p.has(name)]
        if given:
            raise PluginParameterError(
                f"grid_medium: parameter '{given[0]}' applies to a 'filename' grid; with "
                "a nested sigma_t volume set it on the volume (e.g. gridvolume's "
                "'filter_type', 'to_world', 'use_grid_bbox')")
        volume = p.volume("sigma_t", 1.0)
        check_volume_range("grid_medium", "sigma_t", volume, 0.0, None)
        return cls(volume)

    def eval(self, mei: mi.MediumInteraction3f, active):
        return self.volume.eval(mei, active)

    def bounds(self, multiplier, cells: int, path) -> Bounds:
        data, to_local = placement.volume_grid(self.volume)
        if data is None:
            # A constant (or procedural) volume: one cell over its bounding box. Its
            # minorant is a constant's smallest channel (the largest, once, let
            # decomposition tracking's control exceed a chromatic extinction: the green
            # of (1, 0.2, 1) rendered 10% dark), 0 for any other volume.
            top = np.float32(volume_max(self.volume))
            cell = np.full((1, 1, 1), top, np.float32)
            low = np.full((1, 1, 1), constant_min(self.volume), np.float32)
            return Bounds(cell, low, float(top), placement.bbox_to_local(self.volume.bbox()))
        # Mitsuba's volume holds RGB (evaluated as luminance in mono) or, in spectral
        # variants, the upsampled model (4 channels) already
        values = GridValues(3 if data.shape[3] == MODEL_CHANNELS else data.shape[3])
        if values.gray_only:
            data = values.convert(data)
        builder = new_builder(data.shape, values, multiplier, cells, PARSED_TRANSFORM_MARGIN)
        bounds = built_bounds(builder.add_all(data), to_local)
        # heterogeneous's majorant is scale * volume.max(); keep it bit for bit
        bounds.grid_max = float(np.float32(self.volume.max()))
        return bounds

    def traverse(self, callback) -> None:
        callback.put("sigma_t", self.volume, mi.ParamFlags.Differentiable)

    def changed(self, keys=None) -> None:
        check_volume_range("grid_medium", "sigma_t", self.volume, 0.0, None)

    def describe(self) -> str:
        return ""


# -- nested volumes -------------------------------------------------------------------------
def probe_volume(volume: mi.Volume, n: int, p=None) -> np.ndarray:
    """``volume`` evaluated on ``n`` lanes at points ``p`` (default: its box's centre),
    at wavelengths spread over the visible range in spectral variants: (channels, n)."""
    it = dr.zeros(mi.Interaction3f, n)
    if mi.is_spectral:
        it.wavelengths = probe_wavelengths(n)
    it.p = mi.Point3f(volume.bbox().center()) if p is None else p
    return np.atleast_2d(np.asarray(mi.unpolarized_spectrum(volume.eval(it))))


def volume_max(volume: mi.Volume, slack: float = PROBE_SLACK) -> float:
    """A bound of a volume without grid data: Mitsuba's ``max()``, and in spectral
    variants also the largest value over the visible range (Mitsuba's ``max()`` of an
    upsampled rgb constant is not one: 0.84 for (1, 0.2, 1), whose spectrum reaches
    0.9998), read at the centre of its box, times ``1 + slack`` (a majorant's margin; 0
    for a range check: an albedo of 1 upsamples to at most 1.0 exactly)."""
    vmax = float(volume.max())
    if mi.is_spectral:
        vmax = max(vmax, float(probe_volume(volume, 256).max()) * (1 + slack))
    return vmax


#: random points (times the probe wavelengths) at which a volume without grid data is
#: checked for differing channels
CHANNEL_PROBES = 4096


def volume_channels(volume: mi.Volume) -> int:
    """3 where a nested volume's values can differ between channels, else 1.

    ``Volume.channel_count()`` is not enough: a ``constvolume`` reports 0 in every variant
    (an rgb constant too), and a ``gridvolume`` of RGB data 0 in spectral variants, where
    it holds the upsampled model. Treated as gray, a chromatic extinction rendered wrong
    silently. A grid's data say it; a volume without data is evaluated at random points
    of its box (and at wavelengths over the visible range in spectral variants), exact
    for a constant; a procedural volume gray at every probe counts as gray."""
    count = volume.channel_count()
    if count in (1, 3):
        return count
    data, _ = placement.volume_grid(volume, need_transform=False)
    if data is not None:
        return 3 if data.shape[3] in (3, MODEL_CHANNELS) else 1
    box = volume.bbox()
    lo, hi = np.array(box.min, np.float64), np.array(box.max, np.float64)
    lo, hi = np.where(np.isfinite(lo), lo, -1.0), np.where(np.isfinite(hi), hi, 1.0)
    u = np.random.default_rng(0).random((3, CHANNEL_PROBES))
    values = probe_volume(volume, CHANNEL_PROBES, mi.Point3f(
        *[mi.Float((lo[k] + u[k] * (hi[k] - lo[k])).astype(np.float32)) for k in range(3)]))
    return 3 if np.any(values.max(axis=0) != values.min(axis=0)) else 1


def constant_min(volume: mi.Volume, slack: float = PROBE_SLACK) -> float:
    """A lower bound of a ``constvolume``: its smallest channel (over the visible range in
    spectral variants, probed as :func:`volume_max` does) times ``1 - slack``; 0 for any
    other volume, whose values are not known everywhere."""
    if volume.class_name() != "ConstVolume":
        return 0.0
    return max(float(probe_volume(volume, 256).min()) * (1 - slack), 0.0)


def check_volume_range(plugin: str, name: str, volume: mi.Volume, lo: float,
                       hi: float | None) -> None:
    """Every value of a volume parameter in [lo, hi]: a grid volume voxel by voxel (over
    the wavelengths of its upsampled RGB in spectral variants), another by its bound."""
    data, _ = placement.volume_grid(volume, need_transform=False)
    if data is not None:
        if mi.is_spectral and data.shape[3] == MODEL_CHANNELS:
            # Mitsuba's upsampled RGB: check the values it takes over the wavelengths
            gridio.check_values(f"<{name} volume>", name, data, -np.inf)   # finite
            s_min, s_max = model_range(data)
            data = np.stack([s_min * data[..., 3], s_max * data[..., 3]], axis=-1)
        gridio.check_values(f"<{name} volume>", name, data, lo, hi)
        return
    vmax = volume_max(volume, slack=0.0)
    if not np.isfinite(vmax) or (hi is not None and vmax > hi):
        raise PluginParameterError(
            f"{plugin}: parameter '{name}' has maximum {vmax:g}; allowed: values in "
            f"[{lo:g}, {'inf' if hi is None else f'{hi:g}'}]")
