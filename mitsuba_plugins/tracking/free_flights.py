"""Free-flight rules of the one walk (docs/method.md section 8): where a path's next real
collision in a heterogeneous medium is, and what it weighs.

* :class:`DeltaTracking`: the null-scattering formulation with spectral MIS for
  chromatic extinction (Miller, Georgiev and Jarosz 2019, sec. 5; pbrt-v4's
  ``VolPathIntegrator`` keeps the same ``r_u`` ratios);
* :class:`DecompositionTracking`: a second exponential clock for the control extinction
  (Kutz, Habel, Li and Novak 2017), a rule with a clock of its own.

Both subclass :class:`mitsuba_plugins.tracking.null_collision.NullCollisionRule`; they are listed by
name in :data:`FREE_FLIGHTS` (``volpath_delta``'s ``free_flight`` parameter). A new
free-flight estimator is one rule class here, its entry in the table and its tests.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.tracking.homogeneous import FreeFlight
from mitsuba_plugins.tracking.null_collision import NullCollisionRule
from mitsuba_plugins.tracking.replay import attached
from mitsuba_plugins.tracking.trackers import index_channel, medium_interaction

VARIANT = mi.variant()


def spectral_decision(beta, r_u, hero, collide, real, p_real, p_null, sigma_s):
    """Throughput and spectral-MIS ratios after a tentative collision that the hero
    channel decided: real with per-channel decision densities ``p_real`` (then
    ``beta`` takes ``sigma_s / p_real[h]``), null with ``p_null`` (``beta`` takes
    ``p_null / p_null[h]``); ``r_u`` takes every channel's density over the hero's.
    Both are then divided by ``mean(r_u)``, so ``beta`` *is* the effective throughput
    and ``r_u[h]`` stays positive (Miller, Georgiev and Jarosz 2019). Returns
    ``(beta, r_u)``, unchanged off ``collide``."""
    p_real_h = index_channel(p_real, hero)
    ratio = dr.select(real, p_real / p_real_h, p_null / index_channel(p_null, hero))
    beta = dr.select(collide, beta * dr.select(real, sigma_s / p_real_h, ratio), beta)
    r_u = dr.select(collide, r_u * ratio, r_u)
    norm = dr.rcp(dr.mean(r_u))
    return dr.select(collide, beta * norm, beta), dr.select(collide, r_u * norm, r_u)


class DeltaState:
    DRJIT_STRUCT = {"tau": mi.Float,          # optical depth to the next collision
                    "beta": mi.Spectrum,      # throughput
                    "r_u": mi.Spectrum,       # decision-pdf ratios (spectral MIS)
                    "L_e": mi.Spectrum,       # medium emission collected
                    "scattered": mi.Bool}     # stopped at a real collision

    def __init__(self, tau=None, beta=None, r_u=None, L_e=None, scattered=None):
        self.tau, self.beta, self.r_u, self.L_e, self.scattered = tau, beta, r_u, L_e, scattered


class ReplayDeltaState(DeltaState):
    """:class:`DeltaState` in a gradient replay: plus the forward-mode tangent."""
    DRJIT_STRUCT = dict(DeltaState.DRJIT_STRUCT, grad=mi.Spectrum)

    def __init__(self, tau=None, beta=None, r_u=None, L_e=None, scattered=None, grad=None):
        super().__init__(tau, beta, r_u, L_e, scattered)
        self.grad = grad


class DeltaTracking(NullCollisionRule):
    r"""Free flight: the next real collision (docs/method.md section 8). At a
    tentative collision at ``x``:

    * gray: real with probability ``sigma_t / sigma_maj``, weight ``sigma_s / sigma_t``;
      null otherwise, weight 1.
    * ``chromatic``: the hero channel ``h`` decides, real with probability
      ``sigma_t[h] / sigma_maj``; ``beta`` gets ``sigma_s / sigma_t[h]`` (real) or
      ``sigma_n / sigma_n[h]`` (null) and ``r_u`` the ratios of every channel's decision
      pdf to the hero's. The path's contribution ``beta / mean(r_u)`` is the balance
      heuristic over which channel was hero (one-sample MIS). After each collision
      ``beta`` and ``r_u`` are divided by ``mean(r_u)``, so ``beta`` *is* the effective
      throughput and ``r_u[h]`` stays positive.

    With ``emission``, every tentative collision adds ``beta sigma_a Le / sigma_maj``
    (its expectation is ``int T sigma_a Le dt``; section 6's convention). The walk
    returns a :class:`FreeFlight`.

    ``replay`` (a :class:`~mitsuba_plugins.tracking.replay.Replay`, gradients only) with
    ``remaining``, the radiance the path gathers from the flight's start on: each step
    and collision also propagates the derivative of its weight
    (:mod:`mitsuba_plugins.tracking.replay`).
    """
    label = "delta_tracking"
    budget = "beta"
    flight = True

    def __init__(self, beta: mi.Spectrum, r_u: mi.Spectrum, hero: mi.UInt32, chromatic: bool,
                 emission: bool, replay=None, remaining: mi.Spectrum = None):
        self.beta, self.r_u, self.hero = beta, r_u, hero
        self.chromatic, self.emission = chromatic, emission
        self.replay, self.remaining = replay, remaining

    def start(self, tracker, ray, t_in, t_out, sampler, active):
        state = (-dr.log(1.0 - sampler.next_1d(active)), mi.Spectrum(self.beta),
                 mi.Spectrum(self.r_u), mi.Spectrum(0.0), mi.Bool(False))
        if self.replay is None:
            return DeltaState(*state)
        return ReplayDeltaState(*state, mi.Spectrum(0.0))

    def travel(self, tracker, ray, t, state, seg, step, active):
        # the gradient rule's part of the step, in front of all gathered after it
        if self.replay is not None:
            grad = self.replay.flight.travel(self.replay, tracker, ray, t, step,
                                             self.remaining - state.L_e, active)
            if grad is not None:
                state.grad += grad

    def replay_collision(self, tracker, ray, t, sigma_maj, beta, state, collide, real):
        """The derivative of a tentative collision's weights: the light it gathers,
        then the real collision's ``sigma_s`` and what the gradient rule says of a null
        one (``replay.flight``), in front of all gathered after it."""
        replay = self.replay
        props = attached(lambda: tracker.properties(medium_interaction(ray, t), collide))
        if self.emission:
            state.grad += replay.emit(attached(
                lambda: beta * (props.sigma_t - props.sigma_s) * props.Le / sigma_maj), collide)
        after = self.remaining - state.L_e
        state.grad += replay.factor(props.sigma_s, after, replay.flight.scattering(replay, real))
        grad = replay.flight.null_collision(replay, sigma_maj, props, after, collide & ~real)
        if grad is not None:
            state.grad += grad

    def gather(self, state, props, rate, collide) -> None:
        """With ``emission``: the light of a tentative collision drawn at ``rate``,
        ``beta sigma_a Le / rate``."""
        if self.emission:
            state.L_e = dr.select(collide, state.L_e + state.beta * (
                props.sigma_t - props.sigma_s) * props.Le / rate, state.L_e)

    def collide(self, tracker, ray, sampler, t, sigma_maj, rate, state, collide):
        props = tracker.properties(medium_interaction(ray, t), collide)
        sigma_t, sigma_s = props.sigma_t, props.sigma_s
        sigma_n = dr.maximum(sigma_maj - sigma_t, 0.0)
        beta = state.beta
        self.gather(state, props, sigma_maj, collide)
        u = sampler.next_1d(collide)
        if self.chromatic:
            real = collide & (u * sigma_maj < index_channel(sigma_t, self.hero))
            state.beta, state.r_u = spectral_decision(beta, state.r_u, self.hero, collide, real,
                                                      sigma_t, sigma_n, sigma_s)
        else:
            real = collide & (u * sigma_maj < sigma_t[0])
            state.beta = dr.select(real, beta * (sigma_s / sigma_t), beta)
        if self.replay is not None:
            self.replay_collision(tracker, ray, t, sigma_maj, beta, state, collide, real)
        state.scattered |= real
        return ~real

    def finish(self, t, state, t_out, entered):
        grad = state.grad if self.replay is not None else None
        return FreeFlight(state.scattered, t, state.beta, state.r_u, state.L_e, grad)


class DecompositionState:
    DRJIT_STRUCT = {"tau": mi.Float,          # residual optical depth to the next collision
                    "tau_c": mi.Float,        # control optical depth to its collision
                    "beta": mi.Spectrum,      # throughput
                    "r_u": mi.Spectrum,       # decision-pdf ratios (spectral MIS)
                    "L_e": mi.Spectrum,       # medium emission collected
                    "scattered": mi.Bool}     # stopped at a real collision

    def __init__(self, tau=None, tau_c=None, beta=None, r_u=None, L_e=None, scattered=None):
        self.tau, self.tau_c, self.beta, self.r_u = tau, tau_c, beta, r_u
        self.L_e, self.scattered = L_e, scattered


#: With emission, decomposition keeps its control below this share of the majorant:
#: emission is gathered at the residual's tentative collisions, which must not vanish
#: where the medium emits.
EMISSIVE_CONTROL_SHARE = 0.5


class DecompositionTracking(DeltaTracking):
    r"""Free flight by decomposition tracking (Kutz, Habel, Li and Novak 2017): the
    extinction splits into a control :math:`\sigma_c` (gray, constant on a majorant
    piece: its minorant, a lower bound of every channel) and a residual
    :math:`\sigma_r = \sigma_t - \sigma_c \ge 0`. Collisions of the control come from
    a clock of their own (one exponential optical depth spent at rate
    :math:`\sigma_c`: no lookup decides them); the residual is delta-tracked against
    :math:`\sigma_{maj} - \sigma_c`. The first real collision of either ends the flight,
    and its weight is the scattering of that component over its density: the albedo
    :math:`\sigma_s / \sigma_t` for both in a gray medium (the same estimator as delta
    tracking, with :math:`\sigma_c / \sigma_{maj}` fewer lookups). Chromatic: the hero
    decides the residual as :class:`DeltaTracking` decides it (densities
    :math:`\sigma_r` real, :math:`\sigma_{maj} - \sigma_t` null); a control collision
    has the same density in every channel, so it leaves ``r_u`` as it is and ``beta``
    takes the albedo per channel. Emission is gathered at the residual's tentative
    collisions (:math:`\beta \sigma_a L_e / (\sigma_{maj} - \sigma_c)`), the control
    then kept below :data:`EMISSIVE_CONTROL_SHARE` of the majorant.
    """
    label = "decomposition_tracking"
    control = True
    clock = True

    def control_extinction(self, tracker, seg) -> mi.Float:
        # the segment's minorant times the tracker's factor that makes it a lower bound
        # of every channel (a chromatic multiplier's minorant is the largest channel's)
        sigma_c = seg.sigma_min * tracker.control_scale
        if self.emission:
            sigma_c = dr.minimum(sigma_c, EMISSIVE_CONTROL_SHARE * seg.sigma_maj)
        return dr.minimum(sigma_c, seg.sigma_maj)

    def start(self, tracker, ray, t_in, t_out, sampler, active):
        tau = -dr.log(1.0 - sampler.next_1d(active))
        tau_c = -dr.log(1.0 - sampler.next_1d(active))
        return DecompositionState(tau, tau_c, mi.Spectrum(self.beta), mi.Spectrum(self.r_u),
                                  mi.Spectrum(0.0), mi.Bool(False))

    def sample_clock(self, tracker, seg, t, step, state, active):
        sigma_c = self.control_extinction(tracker, seg)
        reach = dr.select(sigma_c > 0, state.tau_c / sigma_c, dr.inf)
        ring = active & (reach < step)
        step = dr.select(ring, reach, step)
        state.tau_c = dr.select(active & ~ring, state.tau_c - sigma_c * step, state.tau_c)
        return ring, step

    def ring(self, tracker, ray, sampler, t, state, ring):
        # a control collision's weight is the albedo: no density lookup (grid media)
        albedo = tracker.albedo(medium_interaction(ray, t), ring)
        state.beta = dr.select(ring, state.beta * albedo, state.beta)
        state.scattered |= ring
        return ~ring

    def collide(self, tracker, ray, sampler, t, sigma_maj, rate, state, collide):
        props = tracker.properties(medium_interaction(ray, t), collide)
        sigma_t, sigma_s = props.sigma_t, props.sigma_s
        sigma_c = sigma_maj - rate
        sigma_r = dr.maximum(sigma_t - sigma_c, 0.0)
        sigma_n = dr.maximum(sigma_maj - sigma_t, 0.0)
        beta = state.beta
        self.gather(state, props, rate, collide)
        u = sampler.next_1d(collide)
        if self.chromatic:
            real = collide & (u * rate < index_channel(sigma_r, self.hero))
            # the residual's scattering: its share of the medium's, sigma_s sigma_r / sigma_t
            # (mi.Spectrum: dr.select of a spectrum and a float is a plain Array4f in
            # spectral variants, which the loop refuses as the throughput's new type)
            share = mi.Spectrum(sigma_s * sigma_r / dr.select(sigma_t > 0, sigma_t, 1.0))
            state.beta, state.r_u = spectral_decision(beta, state.r_u, self.hero, collide, real,
                                                      sigma_r, sigma_n, share)
        else:
            real = collide & (u * rate < sigma_r[0])
            state.beta = dr.select(real, beta * (sigma_s / sigma_t), beta)
        state.scattered |= real
        return ~real


#: Free-flight estimators by name (``free_flight`` parameter of ``volpath_delta``); each
#: is built per render as ``cls(beta, r_u, hero, chromatic, emission)``.
FREE_FLIGHTS = {"delta": DeltaTracking, "decomposition": DecompositionTracking}

