"""Shadow-ray transmittance through heterogeneous media (docs/method.md section 9): rules of
the one walk (:func:`mitsuba_plugins.tracking.walk.walk`) that subclass
:class:`~mitsuba_plugins.tracking.null_collision.NullCollisionRule`. They differ only in
what a tentative collision does: :class:`RatioTracking`, :class:`ResidualRatioTracking`
(Novak, Selle and Jarosz 2014, the majorant grid's per-cell minorant as control
extinction) and :class:`TrackLength`, listed by name in :data:`TRANSMITTANCE_ESTIMATORS`
(``volpath_delta``'s ``transmittance`` parameter). Homogeneous media need no rule
(:func:`mitsuba_plugins.tracking.homogeneous.homogeneous_transmittance`); the free flights
are :mod:`mitsuba_plugins.tracking.free_flights`.

A new estimator is one rule class, its entry in its table and its tests.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.tracking.null_collision import NullCollisionRule
from mitsuba_plugins.tracking.trackers import Tracker, medium_interaction
from mitsuba_plugins.tracking.walk import walk

VARIANT = mi.variant()

#: Ratio tracking plays Russian roulette once the running estimate drops below this.
RATIO_ROULETTE_THRESHOLD = 0.1
#: ... and then dies with probability max(RATIO_ROULETTE_MIN, 1 - T).
RATIO_ROULETTE_MIN = 0.05


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
