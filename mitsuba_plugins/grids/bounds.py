"""Cell bounds of a grid's values: the per-cell maxima and minima, built slab by slab as a
grid streams in (:class:`MajorantBuilder`; :class:`ProductMajorantBuilder` for a
product of two interpolated factors), that become a medium's majorants
(:func:`mitsuba_plugins.tracking.majorant.derive`, docs/method.md section 8).

A cell's bound is the maximum of the voxels whose values a lookup anywhere in the
cell can reach: trilinear interpolation at local coordinate ``x`` on an axis of
``N`` voxels blends voxels ``floor(xN - 1/2)`` and ``floor(xN - 1/2) + 1`` (clamped),
nearest lookup reads ``floor(xN)``; both are inside the range built here for
``x in [r/R - m, (r+1)/R + m]``, ``m`` a margin in local units that absorbs rounding
in the ray-to-cell mapping. An interpolated value is a convex combination of those
voxels, so it cannot exceed their maximum (up to one rounding, covered by
``ROUNDING``). The same argument bounds it from below by the minimum of those voxels:
the per-cell *minorant* is the control extinction of residual ratio tracking (Novak et
al. 2014). This module imports nothing but NumPy and only bounds.
"""
from __future__ import annotations

import numpy as np

#: relative slack on every cell bound for float rounding in interpolation
ROUNDING = 1e-6


#: ... and on a product of interpolated factors (spectral RGB grids: two blends, their
#: product and the spectrum's evaluation each round; measured: 4.6e-7 above a bound with
#: ROUNDING alone, tests/tracking/test_majorant.py in llvm_ad_spectral)
PRODUCT_ROUNDING = 1e-5


#: default margin (local units) by which each cell's voxel range is widened
MARGIN = 1e-4


def voxel_ranges(voxels: int, cells: int, margin: float = MARGIN) -> tuple:
    """Inclusive voxel index ranges ``(lo, hi)`` (arrays of length ``cells``) that
    trilinear or nearest lookups inside each cell of one axis can read."""
    edges = np.arange(cells + 1, dtype=np.float64) / cells
    lo = np.floor((edges[:-1] - margin) * voxels - 0.5).astype(np.int64)
    hi = np.floor((edges[1:] + margin) * voxels - 0.5).astype(np.int64) + 1
    return np.clip(lo, 0, voxels - 1), np.clip(hi, 0, voxels - 1)


def _reduce_axis(values: np.ndarray, axis: int, ranges: tuple, op=np.max) -> np.ndarray:
    lo, hi = ranges
    parts = [op(values.take(np.arange(a, b + 1), axis=axis), axis=axis) for a, b in zip(lo, hi)]
    return np.stack(parts, axis=axis)


class MajorantBuilder:
    """Per-cell maxima of a ``(Z, Y, X, C)`` grid fed slab by slab (z-slices in order).

    ``weights`` (length C, or a scalar) multiply the channels before the maximum
    over channels is taken: the bound is gray, ``max_c weights_c * value_c``. The
    *minorant* (:meth:`finish_min`) is ``min_c weights_c * value_c`` over the same
    voxels: a lower bound of every channel when the weights are equal; with a chromatic
    multiplier (1-channel data, unequal weights) it is the control of the channel of the
    largest weight (residual ratio tracking is unbiased for any control below the
    majorant, docs/method.md section 9).
    """

    def __init__(self, shape, resolution, weights=1.0, margin: float = MARGIN):
        z, y, x, c = shape
        self.shape = tuple(shape)
        self.resolution = tuple(int(r) for r in resolution)  # (Rx, Ry, Rz)
        rx, ry, rz = self.resolution
        self.weights = np.broadcast_to(np.asarray(weights, dtype=np.float32), (c,)).copy()
        self.ranges = (voxel_ranges(z, rz, margin), voxel_ranges(y, ry, margin),
                       voxel_ranges(x, rx, margin))
        self.per_slice = np.zeros((z, ry, rx), dtype=np.float32)
        self.per_slice_min = np.zeros((z, ry, rx), dtype=np.float32)
        self.max = 0.0

    def add(self, z0: int, slab: np.ndarray) -> None:
        if slab.shape[3] == 1:
            gray = low = slab[..., 0] * self.weights[0]
        else:
            weighted = slab * self.weights
            gray, low = weighted.max(axis=3), weighted.min(axis=3)
        if gray.size:
            self.max = max(self.max, float(gray.max()))
        rows = slice(z0, z0 + slab.shape[0])
        reduced = _reduce_axis(gray, 1, self.ranges[1])
        self.per_slice[rows] = _reduce_axis(reduced, 2, self.ranges[2])
        reduced = _reduce_axis(low, 1, self.ranges[1], np.min)
        self.per_slice_min[rows] = _reduce_axis(reduced, 2, self.ranges[2], np.min)

    def add_all(self, data: np.ndarray, slab: int = 16) -> MajorantBuilder:
        """Feed a whole ``(Z, Y, X, C)`` array."""
        for z0 in range(0, data.shape[0], slab):
            self.add(z0, data[z0:z0 + slab])
        return self

    def finish(self) -> np.ndarray:
        """``(Rz, Ry, Rx)`` float32 cell bounds."""
        cells = _reduce_axis(self.per_slice, 0, self.ranges[0])
        with np.errstate(over="ignore"):   # inf: refused by the medium's checks
            return (cells * np.float32(1 + ROUNDING)).astype(np.float32)

    def finish_min(self) -> np.ndarray:
        """``(Rz, Ry, Rx)`` float32 lower bounds of the extinction in each cell."""
        cells = _reduce_axis(self.per_slice_min, 0, self.ranges[0], np.min)
        return (cells * np.float32(1 - ROUNDING)).astype(np.float32)


class ProductMajorantBuilder(MajorantBuilder):
    """Cell bounds of a product of non-negative factors that a lookup interpolates each on
    its own (an upsampled RGB grid in spectral variants: the blend of the voxels' spectra
    times the blend of their scales, :mod:`mitsuba_plugins.grids.spectra`). A blend is at most
    the largest of the values blended, so the product of the factors' cell maxima
    (times ``weight``, the multiplier's largest value) bounds a cell; the product of
    their minima (times ``weight``, as :class:`MajorantBuilder` weights its minorant)
    is the minorant. ``factors(slab)`` gives ``(upper, lower)``, each ``(k, Y, X, F)``,
    for a slab of stored values."""

    def __init__(self, shape, resolution, factors, weight: float, margin: float = MARGIN):
        super().__init__(shape, resolution, 1.0, margin)
        self.factors, self.weight = factors, weight
        self.per_factor, self.factor_max = None, None

    def add(self, z0: int, slab: np.ndarray) -> None:
        upper, lower = self.factors(slab)
        z, ry, rx = self.per_slice.shape
        if self.per_factor is None:
            count = upper.shape[3]
            self.per_factor = np.zeros((count, z, ry, rx), np.float32)
            self.per_factor_min = np.zeros((count, z, ry, rx), np.float32)
            self.factor_max = np.zeros(count)
        rows = slice(z0, z0 + slab.shape[0])
        for f in range(upper.shape[3]):
            if upper[..., f].size:
                self.factor_max[f] = max(self.factor_max[f], float(upper[..., f].max()))
            reduced = _reduce_axis(upper[..., f], 1, self.ranges[1])
            self.per_factor[f, rows] = _reduce_axis(reduced, 2, self.ranges[2])
            reduced = _reduce_axis(lower[..., f], 1, self.ranges[1], np.min)
            self.per_factor_min[f, rows] = _reduce_axis(reduced, 2, self.ranges[2], np.min)
        self.max = float(np.prod(self.factor_max)) * self.weight

    def finish(self) -> np.ndarray:
        cells = np.prod([_reduce_axis(p, 0, self.ranges[0]) for p in self.per_factor], axis=0)
        with np.errstate(over="ignore"):
            return (cells * np.float32(self.weight) *
                    np.float32(1 + PRODUCT_ROUNDING)).astype(np.float32)

    def finish_min(self) -> np.ndarray:
        cells = np.prod([_reduce_axis(p, 0, self.ranges[0], np.min)
                         for p in self.per_factor_min], axis=0)
        return (cells * np.float32(self.weight) * np.float32(1 - ROUNDING)).astype(np.float32)


def pool(values: np.ndarray, shape, op=np.max) -> np.ndarray:
    """Cell bounds ``(Rz, Ry, Rx)`` carried to a coarser ``shape`` ``(rz, ry, rx)``: each
    coarse cell takes ``op`` (np.max for majorants, np.min for minorants) over every fine
    cell it overlaps, so a bound of the fine grid stays a bound of the coarse one (the
    fine cells' margins included) for any ratio of resolutions."""
    out = np.asarray(values)
    for axis, r in enumerate(shape):
        n = out.shape[axis]
        c = np.arange(r)
        lo, hi = (c * n) // r, -((-(c + 1) * n) // r)     # floor(c n / r), ceil((c+1) n / r)
        out = np.stack([op(out.take(np.arange(a, b), axis=axis), axis=axis)
                        for a, b in zip(lo, hi)], axis=axis)
    return out


def resolution_for(shape, cells: int) -> tuple:
    """(Rx, Ry, Rz): ``cells`` per axis, never more than the axis has voxels."""
    z, y, x = shape[:3]
    return (min(cells, x), min(cells, y), min(cells, z))
