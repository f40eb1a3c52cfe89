"""Free flights and transmittance in participating media (docs/method.md sections 7-9).

* Homogeneous media, analytic (no loop): :func:`homogeneous_free_flight` (chromatic
  extinction weighted by the balance heuristic over the channel that drew the path) and
  :func:`homogeneous_transmittance`.
* Heterogeneous media: rules of the one walk (:func:`mitsuba_plugins.walk.walk`) over a
  medium's majorant segments. :class:`NullCollisionRule` samples tentative collisions
  (one exponential optical depth carried across segments, so crossing a cell costs no
  random number); the rules differ only in what a collision does:

  - free flights (:mod:`mitsuba_plugins.flights`: delta and decomposition tracking,
    table ``FREE_FLIGHTS``);
  - :class:`RatioTracking`, :class:`ResidualRatioTracking` (Novak, Selle and Jarosz 2014,
    the majorant grid's per-cell minorant as control extinction) and
    :class:`TrackLength`: shadow-ray transmittance, listed by name in
    :data:`TRANSMITTANCE_ESTIMATORS`.

A new estimator is one rule class, its entry in its table and its tests.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.contract import Tracker, index_channel, medium_interaction
from mitsuba_plugins.instrument import count
from mitsuba_plugins.walk import MajorantSegments, walk

VARIANT = mi.variant()

#: Ratio tracking plays Russian roulette once the running estimate drops below this.
RATIO_ROULETTE_THRESHOLD = 0.1
#: ... and then dies with probability max(RATIO_ROULETTE_MIN, 1 - T).
RATIO_ROULETTE_MIN = 0.05


def sample_exponential(u: mi.Float, rate: mi.Float) -> mi.Float:
    """Distance with pdf ``rate exp(-rate t)`` (per unit length); ``inf`` when rate is 0."""
    return dr.select(rate > 0, -dr.log(1.0 - u) / rate, dr.inf)


class FreeFlight:
    """Outcome of a flight: whether it ``scattered`` (at ``t``; else it reached the
    end), the throughput ``beta`` and spectral-MIS ratios ``r_u`` after it, and the
    medium light ``L_e`` gathered on the way (already times ``beta``); in a gradient
    replay the forward-mode tangent ``grad`` its weights add (0 otherwise)."""
    DRJIT_STRUCT = {"scattered": mi.Bool, "t": mi.Float, "beta": mi.Spectrum,
                    "r_u": mi.Spectrum, "L_e": mi.Spectrum, "grad": mi.Spectrum}

    def __init__(self, scattered=None, t=None, beta=None, r_u=None, L_e=None, grad=None):
        self.scattered, self.t, self.beta, self.r_u, self.L_e = scattered, t, beta, r_u, L_e
        self.grad = mi.Spectrum(0.0) if grad is None else grad


# -- homogeneous media ----------------------------------------------------------------
def homogeneous_free_flight(sigma_t: mi.Spectrum, t_max: mi.Float, u: mi.Float,
                            chromatic: bool, hero: mi.UInt32 = None, r_u: mi.Spectrum = None):
    """Sample a collision along ``[0, t_max]`` in a homogeneous medium.

    Returns ``(t, scattered, weight, r_u)``: the caller multiplies the throughput by
    ``weight`` (times ``sigma_s`` at a collision). Gray: ``t`` has pdf
    ``sigma_t exp(-sigma_t t)``, so ``weight`` is ``1 / sigma_t`` at a collision and 1
    at ``t_max``.

    ``chromatic``: ``t`` is drawn with the hero channel's extinction and the path is
    weighted by the balance heuristic over which channel drew it, at the level of the
    whole path (:func:`spectral_flight_weight`). At the first vertex (``r_u = 1``) this
    is exactly docs/method.md section 7's channel-averaged pdf; over a path it keeps
    each channel's weight below ``n`` times its own single-channel weight, where
    per-vertex averaging multiplies factors up to ``n`` at every vertex (measured: a
    dense albedo-1 furnace with extinctions 0.05/1/5 renders 0.84 +- 0.02 instead of 1
    at 64 spp). A channel with ``sigma_t = 0`` is legal.
    """
    if not chromatic:
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


# -- rules of the walk: tentative collisions ------------------------------------------
class NullCollisionRule:
    """Tentative collisions at rate ``sigma_maj - sigma_c`` along majorant segments
    (``sigma_c``: the control extinction, :meth:`control_extinction`, when ``control``,
    else 0), one exponential optical depth ``tau`` carried across segments. Subclasses
    say what a collision at ``t`` does (:meth:`collide`), what the rest of the way costs
    (:meth:`travel`) and, with ``clock``, when an event of their own ends a step first
    (:meth:`sample_clock`, :meth:`ring`). The segments they walk follow from ``control``
    (:attr:`segments`: with the minorant when a control needs it)."""
    control = False                 # tentative collisions against sigma_maj - sigma_c
    clock = False                   # a clock of the rule's own (sample_clock, ring)
    flight = False                  # a free flight (counted as one, instrument.counting)

    @property
    def segments(self) -> MajorantSegments:
        return MajorantSegments(minorant=self.control)

    def control_extinction(self, tracker, seg) -> mi.Float:
        """``sigma_c`` on the current piece: its segment's minorant."""
        return seg.sigma_min

    def rate(self, tracker, seg) -> mi.Float:
        """The rate of tentative collisions on the current piece: ``sigma_maj`` (minus the
        control's extinction with ``control``)."""
        return seg.sigma_maj - self.control_extinction(tracker, seg) if self.control else \
            seg.sigma_maj

    def step(self, tracker, ray, sampler, seg, t, state, active):
        rate = self.rate(tracker, seg)
        seg_tau = dr.select(rate > 0, rate * (seg.t_end - t), 0.0)
        collide = active & (state.tau < seg_tau)
        step = dr.select(collide, state.tau / rate, seg.t_end - t)
        if not self.clock:
            self.travel(tracker, ray, t, state, seg, step, active)
            t = dr.select(active, dr.select(collide, t + step, seg.t_end), t)
            state.tau = dr.select(active & ~collide, state.tau - seg_tau, state.tau)
        else:
            # the rule's own clock may ring first: the step ends there, and the tentative
            # collisions' clock keeps the optical depth it has not spent
            ring, step = self.sample_clock(tracker, seg, t, step, state, active)
            collide &= ~ring
            self.travel(tracker, ray, t, state, seg, step, active)
            t = dr.select(active, dr.select(collide | ring, t + step, seg.t_end), t)
            spent = dr.select(rate > 0, rate * step, 0.0)
            state.tau = dr.select(active & ~collide, state.tau - spent, state.tau)
            active = active & self.ring(tracker, ray, sampler, t, state, ring)
        alive = self.collide(tracker, ray, sampler, t, seg.sigma_maj, rate, state, collide)
        active = active & alive
        if self.flight:
            count("flight_tentative", collide)
            count("flight_null", active & collide)
        else:
            count("shadow_tentative", collide)
        redraw = active & collide
        state.tau = dr.select(redraw, -dr.log(1.0 - sampler.next_1d(redraw)), state.tau)
        return t, state, active

    def pass_piece(self, tracker, ray, seg, t, state, active):
        """Cross the rest of the current piece where nothing happens on it (no tentative
        collision, no ring of the clock): the arithmetic of :meth:`step` on those lanes,
        for the walk's tight loop. Returns ``(passed, t, state)``."""
        rate = self.rate(tracker, seg)
        seg_tau = dr.select(rate > 0, rate * (seg.t_end - t), 0.0)
        passed = active & (state.tau >= seg_tau)
        step = seg.t_end - t
        if self.clock:
            ring, _ = self.sample_clock(tracker, seg, t, step, state, passed)
            passed &= ~ring
        self.travel(tracker, ray, t, state, seg, step, passed)
        t = dr.select(passed, seg.t_end, t)
        state.tau = dr.select(passed, state.tau - seg_tau, state.tau)
        return passed, t, state

    def travel(self, tracker, ray, t, state, seg, step, active) -> None:
        """Weight for travelling ``step`` from ``t`` without a tentative collision (none by
        default)."""

    def sample_clock(self, tracker, seg, t, step, state, active):
        """``(ring, step)``: whether the rule's clock rings within ``step`` of ``t`` on the
        ``active`` lanes, and the step shortened to it where it does (with ``clock``)."""
        raise NotImplementedError

    def ring(self, tracker, ray, sampler, t, state, ring) -> mi.Bool:
        """What the clock's event at ``t`` does on the ``ring`` lanes; returns whether
        a lane goes on."""
        raise NotImplementedError


class TransmittanceState:
    DRJIT_STRUCT = {"tau": mi.Float,        # optical depth to the next collision
                    "T": mi.Spectrum}       # transmittance estimate

    def __init__(self, tau=None, T=None):
        self.tau, self.T = tau, T


class RatioTracking(NullCollisionRule):
    """The base of the transmittance rules (their state, result and ``transmittance``).
    ``T *= sigma_n / sigma_maj`` at every tentative collision; Russian roulette once
    ``max(T) < 0.1``: die with ``q = max(0.05, 1 - max(T))``, else ``T /= 1 - q``."""
    label = "ratio_tracking"
    budget = "T"

    def start(self, tracker, ray, t_in, t_out, sampler, active):
        return TransmittanceState(-dr.log(1.0 - sampler.next_1d(active)), mi.Spectrum(1.0))

    def collide(self, tracker, ray, sampler, t, sigma_maj, rate, state, collide):
        sigma_t = tracker.sigma_t(medium_interaction(ray, t), collide)
        sigma_n = dr.maximum(sigma_maj - sigma_t, 0.0)
        T = dr.select(collide, state.T * (sigma_n / rate), state.T)
        T_max = dr.max(T)
        roulette = collide & (T_max < RATIO_ROULETTE_THRESHOLD)
        q = dr.maximum(RATIO_ROULETTE_MIN, 1.0 - T_max)
        dies = sampler.next_1d(roulette) < q
        state.T = dr.select(roulette, dr.select(dies, 0.0, T / (1.0 - q)), T)
        return dr.any(state.T > 0)

    def finish(self, t, state, t_out, entered):
        return state.T

    def transmittance(self, tracker: Tracker, ray: mi.Ray3f, t_max: mi.Float,
                      sampler: mi.Sampler, active: mi.Bool) -> mi.Spectrum:
        """Estimate ``exp(-int_0^t_max sigma_t)`` along ``ray``."""
        return walk(tracker, ray, t_max, sampler, self, active)


class ResidualRatioTracking(RatioTracking):
    """Ratio tracking of the residual ``sigma_t - sigma_c`` against the control
    ``sigma_c`` = the segment's minorant: collisions at rate ``sigma_maj - sigma_c``,
    ``T *= exp(-sigma_c d)`` over each distance ``d`` travelled and ``T *= (sigma_maj -
    sigma_t) / (sigma_maj - sigma_c)`` at each collision (both factors in [0, 1]); exact
    in a cell of constant density."""
    label = "residual_tracking"
    control = True

    def travel(self, tracker, ray, t, state, seg, step, active):
        state.T = dr.select(active, state.T * dr.exp(-seg.sigma_min * step), state.T)


class TrackLength(RatioTracking):
    """Survive a collision with probability ``q = max_c sigma_n / sigma_maj`` and weight
    ``sigma_n / (q sigma_maj)`` (<= 1); for gray media delta tracking's 0/1 estimate."""
    label = "track_length"

    def collide(self, tracker, ray, sampler, t, sigma_maj, rate, state, collide):
        sigma_t = tracker.sigma_t(medium_interaction(ray, t), collide)
        sigma_n = dr.maximum(sigma_maj - sigma_t, 0.0)
        q = dr.max(sigma_n) / sigma_maj
        survive = sampler.next_1d(collide) < q
        state.T = dr.select(collide, state.T * dr.select(survive, sigma_n / (q * sigma_maj), 0.0),
                            state.T)
        return dr.any(state.T > 0)


#: Shadow-ray transmittance estimators by name (``transmittance`` parameter).
TRANSMITTANCE_ESTIMATORS = {"ratio": RatioTracking(), "residual": ResidualRatioTracking(),
                            "track_length": TrackLength()}
