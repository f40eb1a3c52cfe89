"""Free-flight sampling and transmittance estimation in participating media
(docs/method.md sections 7-9).

Vectorised building blocks for the volumetric integrators:

* :func:`homogeneous_free_flight`: analytic distance sampling in a homogeneous medium;
  chromatic extinction is weighted by the balance heuristic over the channel that
  drew the path (one-sample MIS; the channel-averaged pdf at a path's first vertex).
* :func:`delta_tracking`: distance sampling in a heterogeneous medium against the
  segments of a majorant grid (:class:`~mitsuba_plugins.majorant.MajorantGrid`), in the
  null-scattering formulation with spectral MIS for chromatic extinction (Miller,
  Georgiev and Jarosz 2019, sec. 5; pbrt-v4's ``VolPathIntegrator`` keeps the same
  ``r_u`` ratios).
* :func:`transmittance`: shadow-ray transmittance: ratio tracking, residual ratio
  tracking (Novak, Selle and Jarosz 2014) with the majorant grid's per-cell minorant
  as control extinction, or track-length (delta tracking as a 0/1 estimate).
* :class:`SceneMedia`: what a scene's media need (built per render, never cached on a
  plugin), and the per-medium dispatch of the tracking loops.

Distances are ray parameters ``t``; rays handed in here have unit direction, so ``t``
is a length and the pdfs are per unit length.
"""
from __future__ import annotations

from typing import Optional, Protocol

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins.majorant import DDAState, MajorantGrid

VARIANT = mi.variant()

#: Shadow-ray transmittance estimators (``transmittance`` parameter).
TRANSMITTANCE_ESTIMATORS = ("ratio", "residual", "track_length")
#: Benchmark instrumentation: when set (see :func:`count_collisions`), kernels traced
#: afterwards add their null collisions to ``COUNTERS[0]`` (free flight) and
#: ``COUNTERS[1]`` (shadow rays). ``None`` (the default) traces no counting code.
COUNTERS = None
#: Ratio tracking plays Russian roulette once the running estimate drops below this.
RATIO_ROULETTE_THRESHOLD = 0.1
#: ... and then dies with probability max(RATIO_ROULETTE_MIN, 1 - T).
RATIO_ROULETTE_MIN = 0.05
#: A majorant segment of optical depth (sigma_maj x length) above this is walked in
#: pieces with tighter bounds (:meth:`MediumTracker.piece`); below it, plain tracking
#: takes at most this many tentative collisions per segment on average, which is cheaper
#: than pieces (each costs a lookup): at 16 the benchmark's max/mean-100 grid (cells of
#: optical depth 43) was refined and its time per sample rose 1.37x over max/mean 30
#: with the same collision counts. Our scenes' segments stay below 7 (sparse.xml); the
#: hard cases of 1e4 (optical depth ~2000) and beyond are refined.
REFINE_OPTICAL_DEPTH = 256.0
#: Expected tentative collisions in one refined piece (1 minimises pieces + collisions).
PIECE_OPTICAL_DEPTH = 1.0
#: Relative slack on a piece's bound for float rounding (and, on CUDA, the 8-bit
#: fixed-point weights of hardware texture interpolation).
PIECE_SLACK = 1e-5 if not VARIANT.startswith("cuda") else 2.0 ** -7
#: Loop iterations one tracking call may take before every further one is survived
#: only with probability WORK_SURVIVAL (Russian roulette, unbiased: the weight of a
#: survivor is divided by it). Traced only for a medium that can have hot segments
#: (:attr:`MediumTracker.hot`): elsewhere every segment holds at most ~256 tentative
#: collisions and a crossing visits at most Rx + Ry + Rz + 3 segments, so the work is
#: bounded already, and the budget's counter and masked draw would cost 4-6% there
#: (measured on smoke, sparse and chromatic). Media that grid_medium accepts (voxel
#: optical depth <= 1e8) need at most ~1.3e5 on the worst crossing of a hot cell
#: (13 sqrt(1e8)).
WORK_BUDGET = 1 << 18
WORK_SURVIVAL = 0.5


def count_collisions(enable: bool = True):
    """Turn null-collision counting on (a fresh zeroed ``mi.UInt32`` of 2 counters,
    returned) or off. Only kernels traced while it is on count (benchmarks only)."""
    global COUNTERS
    COUNTERS = dr.zeros(mi.UInt32, 2) if enable else None
    if COUNTERS is not None:
        dr.make_opaque(COUNTERS)
    return COUNTERS


def _count(slot: int, active) -> None:
    if COUNTERS is not None:
        dr.scatter_add(COUNTERS, mi.UInt32(1), mi.UInt32(slot), active)


def index_channel(spec, channel: mi.UInt32) -> mi.Float:
    """``spec[channel]`` per lane for a 3-channel spectrum."""
    return dr.select(channel == 0, spec[0], dr.select(channel == 1, spec[1], spec[2]))


def sample_exponential(u: mi.Float, rate: mi.Float) -> mi.Float:
    """Distance with pdf ``rate exp(-rate t)`` (per unit length); ``inf`` when rate is 0."""
    return dr.select(rate > 0, -dr.log(1.0 - u) / rate, dr.inf)


# -- homogeneous media ----------------------------------------------------------------
def homogeneous_free_flight(sigma_t: mi.Spectrum, t_max: mi.Float, u: mi.Float, spectral: bool,
                            hero: mi.UInt32 = None, r_u: mi.Spectrum = None):
    """Sample a collision along ``[0, t_max]`` in a homogeneous medium.

    Returns ``(t, scattered, weight, r_u)``: the caller multiplies the throughput by
    ``weight`` (times ``sigma_s`` at a collision). Gray: ``t`` has pdf
    ``sigma_t exp(-sigma_t t)``, so ``weight`` is ``1 / sigma_t`` at a collision and 1
    at ``t_max``.

    Chromatic (``spectral``): ``t`` is drawn with the hero channel's extinction and the
    path is weighted by the balance heuristic over which channel drew it, at the level
    of the whole path: with ``p_k`` the pdf of this event had channel ``k`` drawn it
    (``sigma_t[k] T_k(t)`` or ``T_k(t_max)``) and ``r_u`` the path's pdf ratios so far
    (mean 1), ``weight = T / mean(r_u p)`` and ``r_u <- r_u p / mean(r_u p)``. At the
    first vertex (``r_u = 1``) this is exactly docs/method.md section 7's channel-
    averaged pdf; over a path it keeps each channel's weight below ``n`` times its own
    single-channel weight, where per-vertex averaging multiplies factors up to ``n``
    at every vertex (measured: a dense albedo-1 furnace with extinctions 0.05/1/5
    renders 0.84 +- 0.02 instead of 1 at 64 spp). Exponentials are taken relative to
    the largest one (the common factor cancels), so extinctions of 1e4 do not
    underflow to 0/0, and a channel with ``sigma_t = 0`` is legal.
    """
    if not spectral:
        s = sigma_t[0]
        t = sample_exponential(u, s)
        scattered = t < t_max
        weight = dr.select(scattered, dr.rcp(s), 1.0)
        return t, scattered, mi.Spectrum(weight), r_u
    t = sample_exponential(u, index_channel(sigma_t, hero))
    scattered = t < t_max
    weight, r_u = spectral_flight_weight(sigma_t * dr.select(scattered, t, t_max), sigma_t,
                                         scattered, r_u)
    return t, scattered, weight, r_u


def spectral_flight_weight(tau: mi.Spectrum, sigma_t: mi.Spectrum, scattered: mi.Bool,
                           r_u: mi.Spectrum):
    """Balance-heuristic weight of a flight drawn with one channel's extinction, over
    which channel drew it (one-sample MIS at the level of the whole path).

    ``tau``: optical depth per channel along the flight; ``sigma_t``: extinction at its
    end (used where ``scattered``). Channel ``k`` would have drawn this event with pdf
    ``p_k = sigma_t[k] T_k`` (collision) or ``T_k`` (passing through), ``T_k =
    exp(-tau[k])``. Returns ``(T / mean(r_u p), r_u p / mean(r_u p))``. Exponentials are
    taken relative to the largest, so optical depths of 1e4 do not give 0/0.
    """
    rel = dr.exp(dr.min(tau) - tau)             # T_k / max_k T_k, in (0, 1]
    p = dr.select(scattered, sigma_t * rel, rel)
    norm = dr.rcp(dr.mean(r_u * p))
    return mi.Spectrum(rel * norm), r_u * p * norm


def homogeneous_transmittance(sigma_t: mi.Spectrum, distance: mi.Float) -> mi.Spectrum:
    """Analytic ``exp(-sigma_t d)`` (0 for an infinite distance)."""
    return dr.exp(-sigma_t * dr.select(dr.isfinite(distance), distance, dr.inf))


# -- heterogeneous media --------------------------------------------------------------
class TrackedMedium(Protocol):
    """The contract between a medium and our integrators' tracking loops.

    A medium class that sets ``PROVIDES_TRACKING = True`` (``grid_medium``) promises:

    * ``majorant_grid``: a :class:`~mitsuba_plugins.majorant.MajorantGrid` whose segments
      bound ``eval_sigma_t`` along any ray (tests/test_majorant.py, test_sparse.py);
    * ``refinement``: ``(voxels per local unit, trilinear)`` when a segment can be hot
      (see :meth:`MediumTracker.piece`), else None;
    * ``eval_sigma_t(mei, active)``, ``eval_albedo(mei, active)`` and
      ``get_radiance(mei, active)`` (``Le``; 0 without emission), per channel;
    * ``has_emission``, ``is_chromatic`` (extinction differs between channels) and
      ``bbox`` (world bounds), plus Mitsuba's ``intersect_aabb``.

    Any other medium (Mitsuba's ``heterogeneous``) is tracked through Mitsuba's own
    interface alone: one global majorant and ``get_scattering_coefficients``.
    """
    PROVIDES_TRACKING: bool
    majorant_grid: MajorantGrid
    refinement: Optional[tuple]
    has_emission: bool
    is_chromatic: bool

    def eval_sigma_t(self, mei, active): ...

    def eval_albedo(self, mei, active): ...

    def get_radiance(self, mei, active): ...


class MediumTracker:
    """What the tracking loops need from one heterogeneous medium: its majorant grid
    (the per-cell bounds of a :class:`TrackedMedium`, or one global majorant for any
    other medium, e.g. Mitsuba's ``heterogeneous``), its bounds and its coefficients."""

    def __init__(self, medium: mi.Medium, extent: float = np.inf):
        self.medium = medium
        self.is_grid = bool(getattr(medium, "PROVIDES_TRACKING", False))
        self.has_emission = bool(medium.has_emission) if self.is_grid else False
        #: extinction differs between channels (Mitsuba's media: as they declare)
        self.is_chromatic = bool(medium.is_chromatic) if self.is_grid else \
            medium.has_spectral_extinction()
        #: diagonal of the medium's world box (None: unbounded, as Mitsuba's media say)
        self.diagonal = _diagonal(medium.bbox) if self.is_grid else None
        #: (voxels per local unit on each axis, interpolation) of a grid whose hot
        #: segments are refined (:meth:`piece`); None: no refinement
        self.voxels = medium.refinement if self.is_grid else None
        #: ``hot``: a segment can hold more than REFINE_OPTICAL_DEPTH tentative
        #: collisions, so a crossing's work is not bounded by construction and tracking
        #: keeps a work budget (``extent``: the longest stretch a ray can travel)
        if self.is_grid:
            self.grid = medium.majorant_grid
            self.hot = self.voxels is not None
        else:
            # One segment over the whole ray: a 1-cell grid whose value equals the
            # global majorant inside and outside. Read back once per render.
            majorant = medium.get_majorant(dr.zeros(mi.MediumInteraction3f))
            value = float(np.max(np.asarray(majorant)))
            self.grid = MajorantGrid(np.full((1, 1, 1), value, np.float32),
                                     mi.ScalarTransform4f(), value)
            self.hot = value * extent > REFINE_OPTICAL_DEPTH

    def bounds(self, ray: mi.Ray3f, t_max: mi.Float):
        """``[tmin, tmax]`` of the ray inside the medium's box, clipped to ``[0, t_max]``."""
        hit, t0, t1 = self.medium.intersect_aabb(ray)
        tmin = dr.clip(t0, 0.0, t_max)
        tmax = dr.clip(t1, 0.0, t_max)
        return tmin, dr.select(hit & (tmin < tmax), tmax, tmin)

    def sigma_t(self, mei: mi.MediumInteraction3f, active) -> mi.Spectrum:
        if self.is_grid:
            return mi.Spectrum(self.medium.eval_sigma_t(mei, active))
        _, _, sigma_t = self.medium.get_scattering_coefficients(mei, active)
        return mi.Spectrum(sigma_t)

    def coefficients(self, mei: mi.MediumInteraction3f, active):
        """``(sigma_t, sigma_s, Le)`` at ``mei.p`` (``Le`` is 0 without emission)."""
        if self.is_grid:
            sigma_t = mi.Spectrum(self.medium.eval_sigma_t(mei, active))
            sigma_s = sigma_t * mi.Spectrum(self.medium.eval_albedo(mei, active))
            if self.has_emission:
                return sigma_t, sigma_s, mi.Spectrum(self.medium.get_radiance(mei, active))
            return sigma_t, sigma_s, mi.Spectrum(0.0)
        sigma_s, _, sigma_t = self.medium.get_scattering_coefficients(mei, active)
        return mi.Spectrum(sigma_t), mi.Spectrum(sigma_s), mi.Spectrum(0.0)


    def gray_sigma_t(self, ray: mi.Ray3f, t: mi.Float, active) -> mi.Float:
        return dr.max(self.sigma_t(medium_interaction(ray, t), active))

    def piece(self, ray: mi.Ray3f, dda: DDAState, t: mi.Float, t_cell: mi.Float,
              sigma_cell: mi.Float, active):
        r"""A piece ``[t, t1]`` of a hot majorant segment ``[t, t_cell]`` and a bound of
        the extinction on it, tighter than the segment's ``sigma_cell``: ``(t1, bound)``.

        Trilinear: along the ray the interpolated extinction is Lipschitz with constant
        :math:`G = \sigma_{cell} \sum_i N_i |d_i|` (``d`` the local direction, ``N_i``
        voxels per local unit: neighbouring voxels in the cell differ by at most
        ``sigma_cell``, all values being >= 0), so on ``[t, t + l]``
        :math:`\sigma \le \sigma(t) + G l`. The length makes the piece's optical depth
        :math:`(\sigma(t) + G l) l` equal :data:`PIECE_OPTICAL_DEPTH`. In empty space
        beside one dense voxel the walk then costs about :math:`2 L \sqrt{G}`
        iterations over a length ``L`` instead of :math:`\sigma_{cell} L` null collisions.

        Nearest: the piece runs to the exit of the voxel ahead of ``t``, whose value
        bounds it exactly (read at two points, so a rounding at the entry face cannot
        pick the neighbour alone).
        """
        resolution, trilinear = self.voxels
        floor = (dr.abs(t) + dr.abs(t_cell)) * 2.0 ** -22 + 1e-30   # float32 must move on
        if trilinear:
            sigma0 = self.gray_sigma_t(ray, t, active)
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
            bound = dr.maximum(self.gray_sigma_t(ray, ahead, active),
                               self.gray_sigma_t(ray, 0.5 * (t + t1), active))
            bound *= 1.0 + PIECE_SLACK
        return t1, dr.minimum(bound, sigma_cell)


def medium_interaction(ray: mi.Ray3f, t: mi.Float) -> mi.MediumInteraction3f:
    """A medium interaction at ``ray(t)`` (coefficient lookups, phase functions)."""
    mei = dr.zeros(mi.MediumInteraction3f)
    mei.t = t
    mei.p = ray(t)
    mei.wi = -ray.d
    mei.sh_frame = mi.Frame3f(mei.wi)
    mei.time = ray.time
    mei.wavelengths = ray.wavelengths
    return mei


class FreeFlight:
    """Outcome of :func:`delta_tracking`."""
    DRJIT_STRUCT = {"scattered": mi.Bool, "t": mi.Float, "beta": mi.Spectrum,
                    "r_u": mi.Spectrum, "L_e": mi.Spectrum}

    def __init__(self, scattered=None, t=None, beta=None, r_u=None, L_e=None):
        self.scattered, self.t, self.beta, self.r_u, self.L_e = scattered, t, beta, r_u, L_e


class Segment:
    """Loop state of a walk through a medium's majorant segments: the current piece
    (the whole segment, or a refined part of a hot one) and the segment it is cut from."""
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

    @staticmethod
    def start(tracker: MediumTracker, ray: mi.Ray3f, tmin, tmax, active) -> "Segment":
        return Segment(mi.Float(tmin), mi.Float(0.0), mi.Float(tmin), mi.Float(0.0),
                       mi.Float(0.0), tracker.grid.start(ray, tmin, tmax, active))


def _advance_segment(tracker: MediumTracker, ray: mi.Ray3f, seg: Segment, t, active,
                     minorant: bool):
    """Where position ``t`` has used up its piece, take the next one: the rest of a hot
    segment in refined pieces, or the next majorant segment (lanes whose DDA is
    exhausted leave). Returns ``(active, fetched, seg)``; ``fetched``: a new segment
    (and its ``sigma_min``, 0 without ``minorant``) was taken."""
    exhausted = t >= seg.t_end
    refine = tracker.voxels is not None
    # without refinement a piece is its whole segment (t_end == t_cell)
    need_cell = exhausted & (t >= seg.t_cell) if refine else exhausted
    active = active & ~(need_cell & (seg.dda.t >= seg.dda.t_end))
    fetch = active & need_cell
    _, t1, maj, low, dda = tracker.grid.next_bounds(seg.dda, fetch, minorant=minorant)
    t_cell = dr.select(fetch, t1, seg.t_cell)
    sigma_cell = dr.select(fetch, maj, seg.sigma_cell)
    sigma_min = dr.select(fetch, low, seg.sigma_min) if minorant else seg.sigma_min
    if not refine:
        return active, fetch, Segment(t_cell, sigma_cell, t_cell, sigma_cell, sigma_min, dda)
    new_piece = active & exhausted
    t_end = dr.select(new_piece, t_cell, seg.t_end)
    sigma_maj = dr.select(new_piece, sigma_cell, seg.sigma_maj)
    hot = new_piece & (sigma_cell * (t_cell - t) > REFINE_OPTICAL_DEPTH)
    t_piece, bound = tracker.piece(ray, dda, t, t_cell, sigma_cell, hot)
    t_end[hot] = t_piece
    sigma_maj[hot] = bound
    return active, fetch, Segment(t_end, sigma_maj, t_cell, sigma_cell, sigma_min, dda)


def _work_budget(tracker: MediumTracker, work: mi.UInt32, sampler: mi.Sampler, active,
                 weight):
    """One iteration of a tracking loop against :data:`WORK_BUDGET` (only for a hot
    medium; elsewhere nothing is traced): past it, the iteration survives with
    probability :data:`WORK_SURVIVAL` and ``weight`` (the throughput or transmittance)
    is divided by it, or the lane stops with weight 0. Returns ``(work, weight, active)``."""
    if not tracker.hot:
        return work, weight, active
    work = work + 1
    over = active & (work > WORK_BUDGET)
    dies = over & (sampler.next_1d(over) >= WORK_SURVIVAL)
    weight = dr.select(dies, 0.0, dr.select(over, weight * (1.0 / WORK_SURVIVAL), weight))
    return work, weight, active & ~dies


@dr.syntax
def delta_tracking(tracker: MediumTracker, ray: mi.Ray3f, t_max: mi.Float, sampler: mi.Sampler,
                   beta: mi.Spectrum, r_u: mi.Spectrum, hero: mi.UInt32, spectral: bool,
                   emission: bool, active: mi.Bool) -> FreeFlight:
    r"""Sample the next real collision along ``ray`` over ``[0, t_max]``.

    Tentative collisions follow the majorant grid's segments; one exponential optical
    depth carries over segment boundaries, so crossing a cell costs no random number.
    At a tentative collision at ``x`` (docs/method.md section 8):

    * gray (``spectral`` false): real with probability ``sigma_t / sigma_maj``, weight
      ``sigma_s / sigma_t``; null otherwise, weight 1.
    * chromatic: the hero channel ``h`` decides, real with probability
      ``sigma_t[h] / sigma_maj``; ``beta`` gets ``sigma_s / sigma_t[h]`` (real) or
      ``sigma_n / sigma_n[h]`` (null) and ``r_u`` the ratios of every channel's
      decision pdf to the hero's, ``sigma_t / sigma_t[h]`` or ``sigma_n / sigma_n[h]``.
      The path's contribution ``beta / mean(r_u)`` is the balance heuristic over which
      channel was hero (one-sample MIS). After each collision ``beta`` and ``r_u`` are
      divided by ``mean(r_u)``, so ``beta`` *is* the effective throughput and
      ``r_u[h]`` stays positive; each weight is then at most ``n`` channels.

    With ``emission``, every tentative collision adds ``beta sigma_a Le / sigma_maj``
    (its expectation is ``int T sigma_a Le dt``; section 6's convention).
    """
    tmin, tmax = tracker.bounds(ray, t_max)

    # ------------------------------ loop state ------------------------------
    t = mi.Float(tmin)                                  # current position on the ray
    seg = Segment.start(tracker, ray, tmin, tmax, active)  # current piece and segment
    tau = -dr.log(1.0 - sampler.next_1d(active))        # optical depth to the next collision
    beta = mi.Spectrum(beta)                            # throughput
    r_u = mi.Spectrum(r_u)                              # decision-pdf ratios (spectral MIS)
    L_e = mi.Spectrum(0.0)                              # medium emission collected
    scattered = mi.Bool(False)                          # stopped at a real collision
    work = mi.UInt32(0)                                 # iterations so far (work budget)
    active = mi.Bool(active) & (tmin < tmax)

    while dr.hint(active, label="delta_tracking"):
        # ------------------- bounded work: roulette past the budget -------------------
        work, beta, active = _work_budget(tracker, work, sampler, active, beta)

        # ------------------- next piece or majorant segment when used up -------------------
        active, _, seg = _advance_segment(tracker, ray, seg, t, active, minorant=False)
        t_seg, sigma_maj = seg.t_end, seg.sigma_maj

        # --------------- tentative collision in this piece, or move on ---------------
        seg_tau = dr.select(sigma_maj > 0, sigma_maj * (t_seg - t), 0.0)
        collide = active & (tau < seg_tau)
        t[active] = dr.select(collide, t + tau / sigma_maj, t_seg)
        tau[active & ~collide] = tau - seg_tau

        mei = medium_interaction(ray, t)
        sigma_t, sigma_s, Le = tracker.coefficients(mei, collide)
        sigma_n = dr.maximum(sigma_maj - sigma_t, 0.0)
        if dr.hint(emission, mode="scalar"):
            L_e[collide] += beta * (sigma_t - sigma_s) * Le / sigma_maj

        # ----------------------- real or null collision -----------------------
        u = sampler.next_1d(collide)
        if dr.hint(spectral, mode="scalar"):
            sigma_t_h = index_channel(sigma_t, hero)
            real = collide & (u * sigma_maj < sigma_t_h)
            ratio = dr.select(real, sigma_t / sigma_t_h, sigma_n / index_channel(sigma_n, hero))
            beta[collide] *= dr.select(real, sigma_s / sigma_t_h, ratio)
            r_u[collide] *= ratio
            norm = dr.rcp(dr.mean(r_u))
            beta[collide] *= norm
            r_u[collide] *= norm
        else:
            real = collide & (u * sigma_maj < sigma_t[0])
            beta[real] *= sigma_s / sigma_t
        scattered |= real
        active &= ~real
        _count(0, active & collide)
        tau[active & collide] = -dr.log(1.0 - sampler.next_1d(active & collide))

    return FreeFlight(scattered, t, beta, r_u, L_e)


@dr.syntax
def transmittance(tracker: MediumTracker, ray: mi.Ray3f, t_max: mi.Float, sampler: mi.Sampler,
                  method: str, active: mi.Bool) -> mi.Spectrum:
    r"""Unbiased estimate of ``exp(-int_0^t_max sigma_t)`` along ``ray`` (docs/method.md
    section 9), ``method`` one of :data:`TRANSMITTANCE_ESTIMATORS`:

    * ``ratio``: at every tentative collision ``T *= sigma_n / sigma_maj``;
    * ``residual``: control extinction ``sigma_c`` = the cell's minorant; tentative
      collisions at rate ``sigma_maj - sigma_c``, ``T *= exp(-sigma_c d)`` over each
      distance ``d`` travelled and ``T *= (sigma_maj - sigma_t) / (sigma_maj - sigma_c)``
      at each collision (both factors in [0, 1]); in a cell of constant density the
      estimate is exact;
    * ``track_length``: survive a collision with probability
      ``q = max_c sigma_n / sigma_maj`` and weight ``sigma_n / (q sigma_maj)`` (<= 1);
      for gray media this is delta tracking's 0/1 estimate.

    Ratio and residual tracking play Russian roulette once ``max(T) < 0.1``: die with
    ``q = max(0.05, 1 - max(T))``, else ``T /= 1 - q``.
    """
    residual = method == "residual"
    tmin, tmax = tracker.bounds(ray, t_max)

    # ------------------------------ loop state ------------------------------
    T = mi.Spectrum(1.0)                                # transmittance estimate
    t = mi.Float(tmin)                                  # current position on the ray
    seg = Segment.start(tracker, ray, tmin, tmax, active)  # current piece and segment
    sigma_c = mi.Float(0.0)                             # segment control extinction
    tau = -dr.log(1.0 - sampler.next_1d(active))        # optical depth to the next collision
    work = mi.UInt32(0)                                 # iterations so far (work budget)
    active = mi.Bool(active) & (tmin < tmax)

    while dr.hint(active, label="transmittance"):
        work, T, active = _work_budget(tracker, work, sampler, active, T)

        active, fetch, seg = _advance_segment(tracker, ray, seg, t, active, minorant=residual)
        t_seg, sigma_maj = seg.t_end, seg.sigma_maj
        if dr.hint(residual, mode="scalar"):
            sigma_c[fetch] = seg.sigma_min

        rate = sigma_maj - sigma_c
        seg_tau = dr.select(rate > 0, rate * (t_seg - t), 0.0)
        collide = active & (tau < seg_tau)
        step = dr.select(collide, tau / rate, t_seg - t)
        if dr.hint(residual, mode="scalar"):
            T[active] *= dr.exp(-sigma_c * step)
        t[active] += step
        tau[active & ~collide] = tau - seg_tau

        sigma_t = tracker.sigma_t(medium_interaction(ray, t), collide)
        sigma_n = dr.maximum(sigma_maj - sigma_t, 0.0)
        if dr.hint(method == "track_length", mode="scalar"):
            q = dr.max(sigma_n) / sigma_maj
            survive = sampler.next_1d(collide) < q
            T[collide] *= dr.select(survive, sigma_n / (q * sigma_maj), 0.0)
        else:
            T[collide] *= sigma_n / rate
            T_max = dr.max(T)
            roulette = collide & (T_max < RATIO_ROULETTE_THRESHOLD)
            q = dr.maximum(RATIO_ROULETTE_MIN, 1.0 - T_max)
            dies = sampler.next_1d(roulette) < q
            T[roulette] = dr.select(dies, 0.0, T / (1.0 - q))
        _count(1, collide)
        active &= dr.any(T > 0)
        tau[active & collide] = -dr.log(1.0 - sampler.next_1d(active & collide))

    return T


# -- the media of a scene ---------------------------------------------------------------
def _is_chromatic(medium: mi.Medium) -> bool:
    if not medium.has_spectral_extinction():
        return False
    _, _, sigma_t = medium.get_scattering_coefficients(dr.zeros(mi.MediumInteraction3f))
    values = np.asarray(sigma_t).ravel()
    return bool(np.ptp(values) > 0)


def _diagonal(bbox) -> float:
    return float(np.linalg.norm(np.array(bbox.max) - np.array(bbox.min)))


def scene_media(scene: mi.Scene) -> list:
    """Distinct media referenced by the scene's shapes and sensors, in scene order."""
    found, seen = [], set()
    candidates = [sensor.get_medium() for sensor in scene.sensors()]
    for shape in scene.shapes():
        candidates += [shape.interior_medium(), shape.exterior_medium()]
    for medium in candidates:
        if medium is not None and id(medium) not in seen:
            seen.add(id(medium))
            found.append(medium)
    return found


class SceneMedia:
    """What the scene's media require, derived at each render (never cached on a
    plugin): which code a kernel needs, and per-medium dispatch of the tracking loops.

    ``any``: the scene has media. ``homogeneous`` / ``heterogeneous``: some medium of
    that kind exists. ``spectral_homogeneous`` / ``spectral``: some homogeneous /
    heterogeneous medium has chromatic extinction. ``emission``: some medium emits.
    """

    def __init__(self, scene: mi.Scene):
        media = scene_media(scene)
        self.scene_extent = _diagonal(scene.bbox())
        self.any = bool(media)
        homogeneous = [m for m in media if m.is_homogeneous()]
        self.trackers = {id(m): MediumTracker(m, self.scene_extent) for m in media
                         if not m.is_homogeneous()}
        self.homogeneous = bool(homogeneous)
        self.heterogeneous = bool(self.trackers)
        multichannel = dr.size_v(mi.Spectrum) > 1
        # Mitsuba's media claim spectral extinction by default; a homogeneous one is
        # chromatic only if its channels differ (read back once per render).
        self.spectral_homogeneous = multichannel and any(_is_chromatic(m) for m in homogeneous)
        self.spectral = multichannel and any(t.is_chromatic for t in self.trackers.values())
        self.emission = any(t.has_emission for t in self.trackers.values())

    def extent(self) -> float:
        """Longest stretch a ray can travel through one heterogeneous medium: the
        largest diagonal of their bounding boxes (the scene's, for media without one)."""
        sizes = [self.scene_extent if t.diagonal is None else t.diagonal
                 for t in self.trackers.values()]
        return max(sizes, default=0.0)

    def call(self, medium: mi.MediumPtr, fn, *args):
        """``fn(tracker, *args)`` for each lane's heterogeneous medium; ``args`` end with
        the lane mask. The caller keeps its own values where the mask is off.

        With several heterogeneous media each one's loop runs on its own lanes, one
        after the other (Dr.Jit 1.5 cannot compile these loops inside ``dr.dispatch``:
        "unhandled node kind call_input"); lanes of the other media leave at once.
        """
        trackers = list(self.trackers.values())
        if len(trackers) == 1:
            return fn(trackers[0], *args)
        *rest, active = args
        result = None
        for tracker in trackers:
            mine = active & (medium == mi.MediumPtr(tracker.medium))
            out = fn(tracker, *rest, mine)
            result = out if result is None else dr.select(mine, out, result)
        return result


def _media_transmittance(media: SceneMedia, medium: mi.MediumPtr, ray: mi.Ray3f, t_max: mi.Float,
                         sampler: mi.Sampler, method: str, active: mi.Bool) -> mi.Spectrum:
    """Transmittance over ``[0, t_max]`` of each lane's current medium: analytic in
    homogeneous media, estimated by ``method`` in heterogeneous ones: the name of one
    of :data:`TRANSMITTANCE_ESTIMATORS`, or an object whose ``transmittance(tracker,
    ray, t_max, sampler, active)`` computes it (e.g. a
    :class:`~mitsuba_plugins.marching.Marcher`)."""
    T = mi.Spectrum(1.0)
    in_medium = active & (medium != None)  # noqa: E711
    homogeneous = mi.Bool(False)
    if media.homogeneous:
        homogeneous = in_medium & medium.is_homogeneous()
        _, _, sigma_t = medium.get_scattering_coefficients(medium_interaction(ray, 0.0), homogeneous)
        T[homogeneous] = homogeneous_transmittance(mi.Spectrum(sigma_t), t_max)
    if media.heterogeneous:
        heterogeneous = in_medium & ~homogeneous
        if isinstance(method, str):
            T_het = media.call(medium, transmittance, ray, t_max, sampler, method, heterogeneous)
        else:
            T_het = media.call(medium, method.transmittance, ray, t_max, sampler, heterogeneous)
        T[heterogeneous] = T_het
    return T


@dr.syntax
def shadow_transmittance(scene: mi.Scene, media: SceneMedia, ref: mi.Interaction3f,
                         ds: mi.DirectionSample3f, medium: mi.MediumPtr, sampler: mi.Sampler,
                         method: str, active: mi.Bool) -> mi.Spectrum:
    """Transmittance from ``ref`` to the emitter sample ``ds`` through media and
    index-matched (``null``) surfaces; any other surface blocks (as in Mitsuba's
    ``volpath``, a surface passes ``eval_null_transmission``)."""
    # ------------------------------ loop state ------------------------------
    ray = ref.spawn_ray(ds.d)                                 # current shadow-ray piece
    remaining = ds.dist * (1.0 - mi.math.ShadowEpsilon)       # distance left to the emitter
    T = mi.Spectrum(1.0)                                      # transmittance so far
    medium = mi.MediumPtr(medium)                             # medium of the current piece
    active = mi.Bool(active)

    while dr.hint(active, label="shadow_ray"):
        ray.maxt = remaining
        si = scene.ray_intersect(ray, mi.RayFlags.All, False, active)
        T[active] *= _media_transmittance(media, medium, ray, dr.minimum(si.t, remaining),
                                          sampler, method, active)
        hit = active & si.is_valid()
        bsdf = si.bsdf(ray)
        T[hit] *= bsdf.eval_null_transmission(si, hit)
        medium[hit & si.is_medium_transition()] = si.target_medium(ray.d)
        remaining[hit] = remaining - si.t
        ray[hit] = si.spawn_ray(ray.d)
        active = hit & dr.any(T != 0) & (remaining > 0)
    return T
