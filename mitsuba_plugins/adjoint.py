r"""Adjoint-driven Russian roulette in media (issue 29; after Vorba and Krivanek 2016,
"Adjoint-Driven Russian Roulette and Splitting in Light Transport Simulation").

Throughput roulette decides by the path's weight :math:`\beta` alone. In a dense medium
of albedo near 1 the weight hardly falls, so a path that wanders deep, where little light
arrives, goes on as long as one near the lit boundary. The expected contribution of a
path from a vertex :math:`x` on is :math:`\beta\,A(x)`, where the *adjoint* :math:`A(x)`
is the radiance a path gathers after :math:`x` per unit weight. With an estimate of
:math:`A`, a path is played on with probability

.. math::

    q = \mathrm{clamp}\Big(\frac{\beta A(x)}{\omega\,P},\ q_{\min},\ 1\Big),
    \qquad P = \max_{\text{vertices so far}} \beta A,

(and never above the throughput rule's survival once that applies), and its weight is
divided by :math:`q`: unbiased for any :math:`A`, since :math:`q` depends only on the
path so far and on data drawn before the render. :math:`P` stands in for Vorba and
Krivanek's pixel estimate (which a sample function does not know): the path's best
expected contribution so far. Without splitting (a megakernel lane cannot fork), only
the lower end of their weight window is used.

:math:`A` is learnt per render by a *pilot* pass: the first samples of the render are
traced with the throughput roulette alone and, at every real vertex in a medium, remember
(a ring of the last :data:`RING` vertices per lane) the cell of a grid over the media's
bounding box and :math:`1 / \beta`; the light the path gathers later is added to those
cells times :math:`1 / \beta` (contributions more than :data:`RING` vertices later are
not, which only lowers :math:`A` deep inside). The pilot's image is part of the render
(the pass is unbiased), so the pilot costs only its bookkeeping.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

VARIANT = mi.variant()

#: Vertices per lane whose later light the pilot adds to their cells.
RING = 8
#: Pilot vertices a cell needs before its estimate is used (else the throughput rule).
MIN_COUNT = 16
#: Pseudo-vertices of the prior (the mean over cells) in each cell's estimate.
PRIOR_COUNT = 16


def media_bounds(scene: mi.Scene):
    """Bounding box of the shapes with an interior medium (None: no such shape)."""
    box = mi.ScalarBoundingBox3f()
    for shape in scene.shapes():
        if shape.interior_medium() is not None:
            box.expand(shape.bbox())
    return box if box.valid() else None


class AdjointGrid:
    """A ``resolution``^3 grid of cells over ``bounds`` (a scalar bounding box)."""

    def __init__(self, bounds, resolution: int):
        lo, hi = mi.ScalarVector3f(bounds.min), mi.ScalarVector3f(bounds.max)
        pad = dr.maximum((hi - lo) * 1e-3, 1e-6)
        self.lo = lo - pad
        self.scale = resolution / ((hi + pad) - self.lo)
        self.resolution = resolution
        self.size = resolution ** 3

    def cell(self, p: mi.Point3f):
        """``(index, inside)`` of the cell holding ``p``."""
        x = (mi.Vector3f(p) - self.lo) * self.scale
        inside = dr.all((x >= 0) & (x < self.resolution))
        i = mi.Vector3u(dr.clip(mi.Vector3i(dr.floor(x)), 0, self.resolution - 1))
        return (i.z * self.resolution + i.y) * self.resolution + i.x, inside


class Learner:
    """The pilot's bookkeeping (one render): per cell the sum of later light over
    :math:`\beta` and the number of vertices. Each lane keeps its last :data:`RING`
    vertices in registers (cell, :math:`1/\beta`, light gathered since) and adds a
    vertex to the grid once, when it leaves the ring or the path ends: one atomic
    addition per vertex, not one per vertex and later event."""

    def __init__(self, grid: AdjointGrid):
        self.grid = grid
        self.total = dr.zeros(mi.Float, grid.size)
        self.count = dr.zeros(mi.Float, grid.size)

    @staticmethod
    def empty_ring():
        """``(cells, weights, gathered)``; a weight of -1 marks an empty slot."""
        return (tuple(mi.UInt32(0) for _ in range(RING)),
                tuple(mi.Float(-1.0) for _ in range(RING)),
                tuple(mi.Float(0.0) for _ in range(RING)))

    def deposit(self, ring, gathered: mi.Float, active):
        """The ring after the path gathered ``gathered`` (channel mean) on ``active``
        lanes."""
        cells, weights, sums = ring
        add = dr.select(active, gathered, 0.0)
        return cells, weights, tuple(dr.fma(dr.maximum(w, 0.0), add, g)
                                     for w, g in zip(weights, sums))

    def _flush(self, cell, weight, gathered, active):
        on = active & (weight >= 0)
        dr.scatter_add(self.total, gathered, cell, on, mode=dr.ReduceMode.Expand)
        dr.scatter_add(self.count, mi.Float(1.0), cell, on, mode=dr.ReduceMode.Expand)

    def push(self, ring, p: mi.Point3f, beta: mi.Spectrum, active):
        """The ring with the vertex at ``p`` (throughput ``beta``) pushed in on ``active``
        lanes inside the grid; the vertex it pushes out goes to the grid."""
        cells, weights, sums = ring
        c, inside = self.grid.cell(p)
        on = active & inside
        self._flush(cells[-1], weights[-1], sums[-1], on)
        b = dr.mean(mi.unpolarized_spectrum(beta))
        w = dr.select(b > 0, dr.rcp(b), 0.0)

        def shift(new, old):
            return tuple(dr.select(on, n, o) for n, o in zip((new,) + old[:-1], old))
        return shift(c, cells), shift(w, weights), shift(mi.Float(0.0), sums)

    def finish(self, ring) -> None:
        """Add what is left in the ring when the path ends."""
        for c, w, g in zip(*ring):
            self._flush(c, w, g, True)

    def guide(self, omega: float, q_min: float) -> "Guide":
        """The estimate learnt: per cell the mean later light per unit weight, shrunk
        towards the mean over all cells by :data:`PRIOR_COUNT` pseudo-vertices (a cell
        seen a few times is mostly the prior); -1 where fewer than :data:`MIN_COUNT`
        vertices were seen."""
        mean = dr.sum(self.total) / dr.maximum(dr.sum(self.count), 1.0)
        adjoint = dr.select(self.count >= MIN_COUNT,
                            (self.total + PRIOR_COUNT * mean) / (self.count + PRIOR_COUNT),
                            -1.0)
        dr.eval(adjoint)
        return Guide(self.grid, adjoint, omega, q_min)


class Guide:
    """The roulette of the module docstring, for one render."""

    def __init__(self, grid: AdjointGrid, adjoint: mi.Float, omega: float, q_min: float):
        self.grid, self.adjoint = grid, adjoint
        # opaque: new values must not make new kernels
        self.omega = dr.opaque(mi.Float, omega)
        self.q_min = dr.opaque(mi.Float, q_min)

    def survival(self, p: mi.Point3f, beta: mi.Spectrum, best: mi.Float, active):
        """``(q, best)``: the survival bound at a vertex at ``p`` (1 where the estimate
        is unknown) and the updated best expected contribution."""
        c, inside = self.grid.cell(p)
        on = active & inside
        a = dr.gather(mi.Float, self.adjoint, c, on)
        known = on & (a >= 0)
        value = dr.mean(mi.unpolarized_spectrum(beta)) * a
        best = dr.select(known, dr.maximum(best, value), best)
        q = dr.clip(value / (self.omega * best), self.q_min, 1.0)
        return dr.select(known & (best > 0), q, 1.0), best
