"""Majorant grid and its DDA traversal (docs/method.md section 8).

A :class:`MajorantGrid` covers a box, the unit cube of a grid's local frame, with
``R_x x R_y x R_z`` cells and stores for each cell an upper bound of the extinction
``sigma_t`` anywhere in it. :meth:`MajorantGrid.start` and :meth:`MajorantGrid.next`
walk a ray through it (a 3D DDA, Amanatides and Woo 1987; pbrt-v4's
``DDAMajorantIterator`` is the same idea) and return successive segments
``[t0, t1)`` with their majorant ``sigma_maj``. The segments tile the requested
``[t_start, t_stop]`` exactly, in order: where the ray runs outside the box (the grid is
clamped there, as Mitsuba's ``gridvolume`` does) the segment carries the global
majorant ``outside``.

A cell's bound is the maximum of the voxels whose values a lookup anywhere in the
cell can reach: trilinear interpolation at local coordinate ``x`` on an axis of
``N`` voxels blends voxels ``floor(xN - 1/2)`` and ``floor(xN - 1/2) + 1`` (clamped),
nearest lookup reads ``floor(xN)``; both are inside the range built here for
``x in [r/R - m, (r+1)/R + m]``, ``m`` a margin in local units that absorbs rounding
in the ray-to-cell mapping. An interpolated value is a convex combination of those
voxels, so it cannot exceed their maximum (up to one rounding, covered by
``ROUNDING``). The same argument bounds it from below by the minimum of those voxels:
the per-cell *minorant* is the control extinction of residual ratio tracking (Novak et
al. 2014). The integrator decides what happens at a tentative collision; this module
only bounds and traverses.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

VARIANT = mi.variant()

#: default cells per axis
DEFAULT_RESOLUTION = 16
#: relative slack on every cell bound for float rounding in interpolation
ROUNDING = 1e-6
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
    times the blend of their scales, :mod:`mitsuba_plugins.spectra`). A blend is at most
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
            return (cells * np.float32(self.weight) * np.float32(1 + ROUNDING)).astype(np.float32)

    def finish_min(self) -> np.ndarray:
        cells = np.prod([_reduce_axis(p, 0, self.ranges[0], np.min)
                         for p in self.per_factor_min], axis=0)
        return (cells * np.float32(self.weight) * np.float32(1 - ROUNDING)).astype(np.float32)


def build_majorants(data: np.ndarray, resolution, weights=1.0, margin: float = MARGIN,
                    slab: int = 16) -> np.ndarray:
    """Cell bounds ``(Rz, Ry, Rx)`` of a whole ``(Z, Y, X, C)`` array."""
    return MajorantBuilder(data.shape, resolution, weights, margin).add_all(data, slab).finish()


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


#: Resolutions per axis the automatic choice (:func:`auto_resolution`) tries.
AUTO_RESOLUTIONS = (1, 2, 4, 8, 16)
#: Cost of one DDA step (one majorant cell crossed) in units of one density lookup (a
#: tentative collision). Fit by hand on the 8 grids of benchmarks/dense.py's family (issue
#: 16), so in-sample: with 1, the resolution chosen had the lowest time per sample of 1-32
#: cells per axis on 7 of them and was within 1% on the eighth, where a fixed 16 (the
#: former default) was up to 1.32x slower (``benchmarks/results/dense_majorant.md``).
CELL_COST = 1.0


def auto_resolution(values: np.ndarray, scale: float, axis_lengths,
                    candidates=AUTO_RESOLUTIONS, cell_cost: float = CELL_COST) -> tuple:
    """The coarsening ``(rz, ry, rx)`` of the cell bounds ``values`` (before ``scale``) that
    minimises the expected work per unit of ray length through the box: density lookups
    (mean majorant x scale x the world length of a local axis, ``axis_lengths``) plus
    ``cell_cost`` per cell crossed (cells per axis). Thin media get few cells (the DDA's
    steps would outnumber the lookups they save), dense heterogeneous ones fine cells."""
    length = float(np.mean(axis_lengths))
    best, best_cost = tuple(values.shape), np.inf
    for n in candidates:
        shape = tuple(min(n, r) for r in values.shape)
        with np.errstate(over="ignore", invalid="ignore"):
            cost = float(np.mean(pool(values, shape))) * scale * length + \
                cell_cost * float(np.mean(shape))
        if cost < best_cost:      # ties keep the coarser; NaN never wins
            best, best_cost = shape, cost
    return best


def resolution_for(shape, cells: int) -> tuple:
    """(Rx, Ry, Rz): ``cells`` per axis, never more than the axis has voxels."""
    z, y, x = shape[:3]
    return (min(cells, x), min(cells, y), min(cells, z))


def ray_box(o: mi.Point3f, d: mi.Vector3f, lo, hi):
    """``(hit, t_near, t_far)``: where the ray ``o + t d`` is inside the axis-aligned box
    ``[lo, hi]`` (slab test; the arithmetic of Mitsuba's ``BoundingBox3f.ray_intersect``).

    Not ``mi.BoundingBox3f(...).ray_intersect(ray)``: Mitsuba binds that class once per
    Dr.Jit backend, for the variant imported first, so after a switch from
    ``llvm_ad_rgb`` to ``llvm_ad_spectral`` it refuses the spectral variant's ``Ray3f``."""
    lo, hi = mi.Point3f(lo), mi.Point3f(hi)
    d_rcp = dr.rcp(d)
    t1 = (lo - o) * d_rcp
    t2 = (hi - o) * d_rcp
    t_near = dr.max(dr.minimum(t1, t2))
    t_far = dr.min(dr.maximum(t1, t2))
    hit = dr.all((d != 0) | ((o > lo) & (o < hi))) & (t_far >= t_near)
    return hit, t_near, t_far


class DDAState:
    """Loop state of one ray's walk through a :class:`MajorantGrid`."""
    DRJIT_STRUCT = {
        "t": mi.Float,        # start of the next segment
        "t_end": mi.Float,    # end of the requested interval (t_stop)
        "t_in": mi.Float,     # where the ray enters the box (clamped to the interval)
        "t_out": mi.Float,    # where it leaves the box (clamped to the interval)
        "cell": mi.Vector3i,  # current cell while inside the box
        "o": mi.Point3f,      # ray origin in the grid's local frame
        "d": mi.Vector3f,     # ray direction in the local frame (not normalised: same t)
    }

    def __init__(self, t=None, t_end=None, t_in=None, t_out=None, cell=None, o=None, d=None):
        self.t, self.t_end, self.t_in, self.t_out = t, t_end, t_in, t_out
        self.cell, self.o, self.d = cell, o, d


class MajorantGrid:
    """Cell bounds of extinction over the unit cube of a local frame, with DDA.

    ``values``: ``(Rz, Ry, Rx)`` bounds; ``to_local``: world -> local transform;
    ``outside``: the bound used where a ray is outside the box (the global majorant);
    ``minorants``: optional ``(Rz, Ry, Rx)`` lower bounds (0 where not given, and
    outside the box). Arrays are evaluated and opaque, so a changed grid never
    recompiles a kernel.
    """

    def __init__(self, values: np.ndarray, to_local, outside: float,
                 minorants: np.ndarray | None = None):
        values = np.asarray(values, dtype=np.float32)
        rz, ry, rx = values.shape
        self.resolution = (rx, ry, rz)
        self.host_values = values
        self.values = mi.Float(values.ravel())
        lows = np.zeros_like(values) if minorants is None else \
            np.minimum(np.asarray(minorants, dtype=np.float32).reshape(values.shape), values)
        self.minorants = mi.Float(lows.ravel())
        self.outside = dr.opaque(mi.Float, float(outside))
        self.to_local = mi.Transform4f(to_local)
        dr.make_opaque(self.values, self.minorants, self.to_local)

    # -- queries -----------------------------------------------------------------
    def empty_fraction(self) -> float:
        """Fraction of the box volume whose bound is exactly 0."""
        return float(np.mean(self.host_values == 0))

    def _index(self, cell: mi.Vector3i) -> mi.UInt32:
        rx, ry, _ = self.resolution
        return mi.UInt32((cell.z * ry + cell.y) * rx + cell.x)

    def _clamp_cell(self, cell: mi.Vector3i) -> mi.Vector3i:
        rx, ry, rz = self.resolution
        return dr.clip(cell, mi.Vector3i(0), mi.Vector3i(rx - 1, ry - 1, rz - 1))

    # -- traversal ---------------------------------------------------------------
    def start(self, ray: mi.Ray3f, t_start: mi.Float, t_stop: mi.Float, active=True) -> DDAState:
        """State for walking ``ray`` over ``[t_start, t_stop]`` (``ray.d`` need not be unit)."""
        o = self.to_local @ ray.o
        d = self.to_local @ ray.d
        hit, t_in, t_out = ray_box(o, d, 0.0, 1.0)
        t_in = dr.clip(t_in, t_start, t_stop)
        t_out = dr.clip(t_out, t_start, t_stop)
        hit &= active & (t_in < t_out)
        t_in = dr.select(hit, t_in, t_stop)
        t_out = dr.select(hit, t_out, t_stop)
        # The cell holding the entry point; a point on a face sits in the cell the
        # ray goes on into, so take the cell of a point just inside.
        res = mi.Vector3f(self.resolution)
        t_mid = dr.select(hit, dr.lerp(t_in, t_out, 1e-4), t_in)
        cell = self._clamp_cell(mi.Vector3i(dr.floor((o + d * t_mid) * res)))
        return DDAState(mi.Float(t_start), mi.Float(t_stop), t_in, t_out, cell, o, d)

    def next(self, state: DDAState, active=True):
        """The next segment: returns ``(t0, t1, sigma_maj, state)``.

        Call while ``state.t < state.t_end``. Segments have ``t1 >= t0`` and the next
        one starts where this one ends; inside the box each is one cell.
        """
        t0, t1, sigma_maj, _, state = self.next_bounds(state, active, minorant=False)
        return t0, t1, sigma_maj, state

    def next_bounds(self, state: DDAState, active=True, minorant: bool = True):
        """As :meth:`next`, with the segment's minorant: ``(t0, t1, sigma_maj,
        sigma_min, state)`` (``sigma_min`` is 0 outside the box or when not asked for)."""
        t0 = mi.Float(state.t)
        before = t0 < state.t_in
        inside = ~before & (t0 < state.t_out)
        res = mi.Vector3f(self.resolution)

        # Parametric distance to the cell's exit face on each axis (inf if parallel).
        positive = state.d > 0
        face = (mi.Vector3f(state.cell) + dr.select(positive, 1.0, 0.0)) / res
        t_face = dr.select(dr.abs(state.d) > 0, (face - state.o) / state.d, dr.inf)
        t_cross = dr.min(t_face)
        t1_inside = dr.maximum(dr.minimum(t_cross, state.t_out), t0)

        index = self._index(state.cell)
        value = dr.gather(mi.Float, self.values, index, active & inside)
        t1 = dr.select(before, state.t_in, dr.select(inside, t1_inside, state.t_end))
        sigma_maj = dr.select(inside, value, self.outside)
        sigma_min = mi.Float(0.0)
        if minorant:
            sigma_min = dr.gather(mi.Float, self.minorants, index, active & inside)

        # Step every axis whose face is crossed at t_cross (corners step several).
        crossing = inside & (t_cross < state.t_out)
        step = dr.select(positive, mi.Vector3i(1), mi.Vector3i(-1))
        cell = mi.Vector3i(state.cell)
        cell += dr.select(crossing & (t_face == t_cross), step, mi.Vector3i(0))
        rx, ry, rz = self.resolution
        left = dr.any((cell < 0) | (cell >= mi.Vector3i(rx, ry, rz)))
        # Leaving the cell range means leaving the box, whatever t_out rounded to.
        t1 = dr.select(inside & left, state.t_out, t1)
        new = DDAState(dr.select(active, t1, state.t), state.t_end, state.t_in,
                       state.t_out, dr.select(active, self._clamp_cell(cell), state.cell),
                       state.o, state.d)
        return t0, t1, sigma_maj, sigma_min, new

    def segments(self, ray: mi.Ray3f, t_start, t_stop, max_segments: int | None = None):
        """All segments as numpy arrays ``(t0, t1, sigma_maj, valid)`` of shape
        ``(n_rays, n_segments)``; for tests and inspection, not for render kernels."""
        rx, ry, rz = self.resolution
        limit = max_segments or (rx + ry + rz + 3)
        state = self.start(ray, mi.Float(t_start), mi.Float(t_stop))
        n = dr.width(ray)
        out = []
        for _ in range(limit):
            active = state.t < state.t_end
            t0, t1, sigma_maj, state = self.next(state, active)
            dr.eval(t0, t1, sigma_maj, active, state.t, state.cell)
            out.append(tuple(np.broadcast_to(np.asarray(x), (n,))
                             for x in (t0, t1, sigma_maj, active)))
        return tuple(np.stack(x, axis=1) for x in zip(*out))
