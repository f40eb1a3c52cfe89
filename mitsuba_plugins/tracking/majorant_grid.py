"""Majorant grid and its DDA traversal (docs/method.md section 8).

A :class:`MajorantGrid` covers a box, the unit cube of a grid's local frame, with
``R_x x R_y x R_z`` cells and stores for each cell an upper bound of the extinction
``sigma_t`` anywhere in it (built by :mod:`mitsuba_plugins.tracking.majorant`).
:meth:`MajorantGrid.start` and :meth:`MajorantGrid.next_bounds` walk a ray through it (a
3D DDA, Amanatides and Woo 1987; pbrt-v4's ``DDAMajorantIterator`` is the same idea) and
return successive segments ``[t0, t1)`` with their majorant ``sigma_maj``. The segments
tile the requested ``[t_start, t_stop]`` exactly, in order: where the ray runs outside the
box (the grid is clamped there, as Mitsuba's ``gridvolume`` does) the segment carries the
global majorant ``outside``.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

VARIANT = mi.variant()


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
        to_world = mi.ScalarTransform4f(to_local).inverse()
        self._line_depth = None     # line_optical_depth, once asked
        #: world length of a cell along x, y, z (host floats)
        origin = to_world @ mi.ScalarPoint3f(0, 0, 0)
        self.cell_lengths = tuple(
            float(dr.norm(to_world @ mi.ScalarPoint3f(*np.eye(3)[k]) - origin)) / n
            for k, n in enumerate((rx, ry, rz)))

    # -- queries -----------------------------------------------------------------
    def line_optical_depth(self) -> float:
        """The largest optical depth of the bounds along a line of cells parallel to an
        axis, times sqrt(3) for oblique rays: what a march across the grid meets, about
        (an estimate, not a bound; a uniform grid gives its bound times its diagonal)."""
        if self._line_depth is None:      # the bounds never change: summed once
            sums = [float(self.host_values.sum(axis=2 - k, dtype=np.float64).max(initial=0.0))
                    * length for k, length in enumerate(self.cell_lengths)]
            self._line_depth = 3 ** 0.5 * max(sums)
        return self._line_depth

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

    def next_bounds(self, state: DDAState, active=True, minorant: bool = True):
        """The next segment: ``(t0, t1, sigma_maj, sigma_min, state)`` (``sigma_min`` is 0
        outside the box or when not asked for). Call while ``state.t < state.t_end``.
        Segments have ``t1 >= t0`` and the next one starts where this one ends; inside the
        box each is one cell."""
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
