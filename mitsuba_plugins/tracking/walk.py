"""One walk along a ray through a heterogeneous medium, with pluggable rules
(pbrt-v4's ``SampleT_maj(ray, tMax, u, rng, callback)`` pattern; docs/method.md 8-10).

:func:`walk` is the only loop over a medium's stretch of a ray. It asks a *segment
iterator* for pieces of the ray and hands each to a *rule*, which decides what happens
in it: sample tentative collisions against the piece's majorant (free flight, ratio /
residual / track-length transmittance: :mod:`mitsuba_plugins.tracking.transmittance`) or treat the
piece as one cell of a march (:mod:`mitsuba_plugins.tracking.marching`).

Segment iterators (``start`` / ``next``):

* :class:`MajorantSegments`: the cells of the medium's majorant grid along the ray
  (a Mitsuba medium is one segment with the global majorant, as in pbrt), hot ones cut
  into refined pieces (:func:`refined_piece`);
* the march cells of :class:`mitsuba_plugins.tracking.marching.Marcher`.

An iterator's state carries ``t_end`` (end of the current piece), and for majorant
segments ``sigma_maj`` and ``sigma_min`` (bounds of the extinction on it). A rule is a
:class:`WalkRule`.

Homogeneous media never reach a walk: their flights and transmittance are analytic
(:mod:`mitsuba_plugins.tracking.homogeneous`), so a scene without heterogeneous media
traces no loop at all.
"""
from __future__ import annotations

from typing import Optional, Protocol

import drjit as dr
import mitsuba as mi

from mitsuba_plugins import instrument
from mitsuba_plugins.loop_state import widened
from mitsuba_plugins.tracking.majorant_grid import DDAState

VARIANT = mi.variant()

#: Expected tentative collisions in one refined piece (1 minimises pieces + collisions).
PIECE_OPTICAL_DEPTH = 1.0
#: Relative slack on a piece's bound for float rounding (and, on CUDA, the 8-bit
#: fixed-point weights of hardware texture interpolation).
PIECE_SLACK = 1e-5 if not VARIANT.startswith("cuda") else 2.0 ** -7
#: Iterations of the outer loop (events and refined pieces; the pieces crossed in the
#: inner loop of :func:`walk` are bounded by the majorant grid's cells) one walk may take
#: before every further one is survived only with probability WORK_SURVIVAL (Russian
#: roulette, unbiased: the weight of a survivor is divided by it). Traced only for a medium that can have hot segments
#: (:attr:`mitsuba_plugins.tracking.trackers.Tracker.hot`): elsewhere every segment holds at most ~256 tentative
#: collisions and a crossing visits at most Rx + Ry + Rz + 3 segments, so the work is
#: bounded already, and the budget's counter and masked draw would cost 4-6% there
#: (measured on smoke, sparse and chromatic). Media that grid_medium accepts (voxel
#: optical depth <= 1e8) need at most ~1.3e5 on the worst crossing of a hot cell
#: (13 sqrt(1e8)).
WORK_BUDGET = 1 << 18
WORK_SURVIVAL = 0.5
class WalkRule(Protocol):
    """What :func:`walk` asks of a rule (free flights, transmittance, marches).

    * ``segments``: the iterator it walks; ``label``: the loop's name;
    * ``budget``: the name of the state field holding the weight that the work budget
      scales (None: the rule's work is bounded by itself);
    * :meth:`start`, :meth:`step`, :meth:`finish` below;
    * optionally ``pass_piece(tracker, ray, seg, t, state, active) -> (passed, t,
      state)``: cross the rest of the current piece on the lanes where nothing happens
      on it (the null-collision rules). The walk then crosses such pieces in a tight
      inner loop with :meth:`MajorantSegments.cross` (no density lookup in it) and
      calls ``step`` only for an event; the random numbers drawn and the images are
      the same as without it.
    """
    segments: object
    label: str
    budget: Optional[str]

    def start(self, tracker, ray, t_in, t_out, sampler, active):
        """The rule's loop state (a ``DRJIT_STRUCT``), drawing what it draws first."""

    def step(self, tracker, ray, sampler, seg, t, state, active):
        """One event inside the current piece ``[t, seg.t_end]``: ``(t, state, active)``."""

    def finish(self, t, state, t_out, entered):
        """The result of the walk."""


@dr.syntax
def walk(tracker, ray: mi.Ray3f, t_max: mi.Float, sampler: mi.Sampler, rule: WalkRule,
         active: mi.Bool):
    """Walk ``ray`` over ``[0, t_max]`` through ``tracker``'s medium, applying ``rule``
    (see the module docstring); returns ``rule.finish(...)``."""
    t_in, t_out = tracker.bounds(ray, t_max)
    segments = rule.segments
    seg = segments.start(tracker, ray, t_in, t_out, sampler, active)
    state = rule.start(tracker, ray, t_in, t_out, sampler, active)
    entered = mi.Bool(active) & (t_in < t_out)

    # ------------------------------ loop state ------------------------------
    t = mi.Float(t_in)                                  # position reached on the ray
    work = mi.UInt32(0)                                 # iterations so far (work budget)
    active = mi.Bool(entered)
    # what the body leaves unchanged must be as wide as the loop (loop_state.widened)
    ray, seg, state, work = (widened(x, entered) for x in (mi.Ray3f(ray), seg, state, work))

    while dr.hint(active, label=rule.label):
        if dr.hint(tracker.hot and rule.budget is not None, mode="scalar"):
            work, active = _work_budget(work, sampler, state, rule.budget, active)
        if dr.hint(hasattr(rule, "pass_piece") and tracker.tight_loop, mode="scalar"):
            # the pieces where nothing happens, crossed in a tight loop of their own: it
            # holds no density lookup, so a step through empty or thin cells costs a
            # fraction of an event (pbrt-v4's SampleT_maj; docs/method.md section 8)
            moving = mi.Bool(active)
            while dr.hint(moving, label=rule.label + "_cross"):
                alive, seg, stop = segments.cross(tracker, ray, seg, t, moving)
                active &= alive | ~moving
                moving &= alive & ~stop
                moving, t, state = rule.pass_piece(tracker, ray, seg, t, state, moving)
                moving &= t < t_out
            active &= t < t_out
            seg = segments.refine(tracker, ray, seg, t, active)
        else:
            active, seg = segments.next(tracker, ray, seg, t, active)
        t, state, active = rule.step(tracker, ray, sampler, seg, t, state, active)
        active &= t < t_out

    return rule.finish(t, state, t_out, entered)


def _work_budget(work: mi.UInt32, sampler: mi.Sampler, state, field: str, active):
    """One iteration against :data:`WORK_BUDGET`: past it, the iteration survives with
    probability :data:`WORK_SURVIVAL` and ``state.<field>`` (the throughput or
    transmittance) is divided by it, or the lane stops with weight 0."""
    work = work + 1
    over = active & (work > WORK_BUDGET)
    dies = over & (sampler.next_1d(over) >= WORK_SURVIVAL)
    weight = getattr(state, field)
    setattr(state, field,
            dr.select(dies, 0.0, dr.select(over, weight * (1.0 / WORK_SURVIVAL), weight)))
    return work, active & ~dies


# -- majorant segments ------------------------------------------------------------------
class Segment:
    """State of :class:`MajorantSegments`: the current piece (the whole segment, or a
    refined part of a hot one) and the segment it is cut from."""
    DRJIT_STRUCT = {"t_end": mi.Float,        # end of the current piece
                    "sigma_maj": mi.Float,    # bound of the extinction on the piece
                    "t_cell": mi.Float,       # end of the current majorant segment
                    "sigma_cell": mi.Float,   # the segment's majorant
                    "sigma_min": mi.Float,    # the segment's minorant (if asked for)
                    "dda": DDAState}          # walk through the majorant grid

    def __init__(self, t_end=None, sigma_maj=None, t_cell=None, sigma_cell=None,
                 sigma_min=None, dda=None):
        self.t_end, self.sigma_maj, self.t_cell = t_end, sigma_maj, t_cell
        self.sigma_cell, self.sigma_min, self.dda = sigma_cell, sigma_min, dda


class MajorantSegments:
    """Segment iterator over a tracker's majorant grid (:class:`MajorantGrid` DDA).
    ``minorant``: also fetch each segment's lower bound (``sigma_min``, else 0)."""

    def __init__(self, minorant: bool = False):
        self.minorant = minorant

    def start(self, tracker, ray: mi.Ray3f, t_in, t_out, sampler, active) -> Segment:
        return Segment(mi.Float(t_in), mi.Float(0.0), mi.Float(t_in), mi.Float(0.0),
                       mi.Float(0.0), tracker.grid.start(ray, t_in, t_out, active))

    def cross(self, tracker, ray: mi.Ray3f, seg: Segment, t, active):
        """:meth:`next` without refinement, for the tight loop of :func:`walk`: where
        ``t`` has used up its piece, the next majorant segment becomes the piece, unless
        it (or the rest of the current one) is hot; then the lane is told to ``stop``,
        holding an empty piece at ``t`` that :meth:`refine` cuts as :meth:`next` would.
        Returns ``(active, seg, stop)``."""
        exhausted = t >= seg.t_end
        refine = tracker.voxels is not None
        # without refinement a piece is its whole segment (t_end == t_cell)
        need_cell = exhausted & (t >= seg.t_cell) if refine else exhausted
        active = active & ~(need_cell & (seg.dda.t >= seg.dda.t_end))
        fetch = active & need_cell
        instrument.count("segments", fetch)
        _, t1, maj, low, dda = tracker.grid.next_bounds(seg.dda, fetch, minorant=self.minorant)
        t_cell = dr.select(fetch, t1, seg.t_cell)
        sigma_cell = dr.select(fetch, maj, seg.sigma_cell)
        sigma_min = dr.select(fetch, low, seg.sigma_min) if self.minorant else seg.sigma_min
        if not refine:
            return active, Segment(t_cell, sigma_cell, t_cell, sigma_cell, sigma_min, dda), \
                mi.Bool(False)
        new_piece = active & exhausted
        stop = new_piece & (sigma_cell * (t_cell - t) > instrument.settings.refine_optical_depth)
        whole = new_piece & ~stop
        t_end = dr.select(whole, t_cell, dr.select(stop, t, seg.t_end))
        sigma_maj = dr.select(new_piece, sigma_cell, seg.sigma_maj)
        return active, Segment(t_end, sigma_maj, t_cell, sigma_cell, sigma_min, dda), stop

    def refine(self, tracker, ray: mi.Ray3f, seg: Segment, t, active) -> Segment:
        """After :meth:`cross`: an empty piece inside a hot segment becomes a refined
        one (the rest of :meth:`next`)."""
        if tracker.voxels is None:
            return seg
        new_piece = active & (t >= seg.t_end) & (t < seg.t_cell)
        t_end = dr.select(new_piece, seg.t_cell, seg.t_end)
        sigma_maj = dr.select(new_piece, seg.sigma_cell, seg.sigma_maj)
        hot = new_piece & (seg.sigma_cell * (seg.t_cell - t) >
                           instrument.settings.refine_optical_depth)
        t_piece, bound = refined_piece(tracker, ray, seg.dda, t, seg.t_cell, seg.sigma_cell, hot)
        t_end[hot] = t_piece
        sigma_maj[hot] = bound
        return Segment(t_end, sigma_maj, seg.t_cell, seg.sigma_cell, seg.sigma_min, seg.dda)

    def next(self, tracker, ray: mi.Ray3f, seg: Segment, t, active):
        """Where position ``t`` has used up its piece, take the next one: the rest of a
        hot segment in refined pieces, or the next majorant segment (lanes whose DDA is
        exhausted leave). Returns ``(active, seg)``: :meth:`cross`, then :meth:`refine`."""
        active, seg, _ = self.cross(tracker, ray, seg, t, active)
        return active, self.refine(tracker, ray, seg, t, active)


def refined_piece(tracker, ray: mi.Ray3f, dda: DDAState, t: mi.Float, t_cell: mi.Float,
                  sigma_cell: mi.Float, active):
    r"""A piece ``[t, t1]`` of a hot majorant segment ``[t, t_cell]`` and a bound of the
    extinction on it, tighter than the segment's ``sigma_cell``: ``(t1, bound)``.

    Trilinear: along the ray the interpolated extinction is Lipschitz with constant
    :math:`G = \sigma_{cell} \sum_i N_i |d_i|` (``d`` the local direction, ``N_i``
    voxels per local unit: neighbouring voxels in the cell differ by at most
    ``sigma_cell``, all values being >= 0), so on ``[t, t + l]``
    :math:`\sigma \le \sigma(t) + G l`. The length makes the piece's optical depth
    :math:`(\sigma(t) + G l) l` equal :data:`PIECE_OPTICAL_DEPTH`. In empty space
    beside one dense voxel the walk then costs about :math:`2 L \sqrt{G}` iterations
    over a length ``L`` instead of :math:`\sigma_{cell} L` null collisions.

    Nearest: the piece runs to the exit of the voxel ahead of ``t``, whose value bounds
    it exactly (read at two points, so a rounding at the entry face cannot pick the
    neighbour alone).
    """
    resolution, trilinear = tracker.voxels
    floor = (dr.abs(t) + dr.abs(t_cell)) * 2.0 ** -22 + 1e-30   # float32 must move on
    if trilinear:
        sigma0 = tracker.gray_sigma_t(ray, t, active)
        G = sigma_cell * dr.sum(resolution * dr.abs(dda.d))
        K = PIECE_OPTICAL_DEPTH
        length = 2.0 * K / (sigma0 + dr.sqrt(dr.square(sigma0) + 4.0 * G * K))
        length = dr.maximum(dr.select(dr.isfinite(length), length, 0.0), floor)
        t1 = dr.minimum(t + length, t_cell)
        bound = (sigma0 + G * (t1 - t)) * (1.0 + PIECE_SLACK) + sigma_cell * PIECE_SLACK
    else:
        ahead = dr.minimum(t + floor, t_cell)
        q = dda.o + dda.d * ahead
        voxel = dr.clip(dr.floor(q * resolution), 0.0, resolution - 1.0)
        face = (voxel + dr.select(dda.d > 0, 1.0, 0.0)) / resolution
        t_face = dr.select(dr.abs(dda.d) > 0, (face - dda.o) / dda.d, dr.inf)
        t1 = dr.minimum(dr.maximum(dr.min(t_face), ahead), t_cell)
        bound = dr.maximum(tracker.gray_sigma_t(ray, ahead, active),
                           tracker.gray_sigma_t(ray, 0.5 * (t + t1), active))
        bound *= 1.0 + PIECE_SLACK
    return t1, dr.minimum(bound, sigma_cell)
