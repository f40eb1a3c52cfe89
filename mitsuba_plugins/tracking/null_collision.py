"""The null-collision rule base of the one walk (:func:`mitsuba_plugins.tracking.walk.walk`): tentative
collisions against a medium's majorant segments, one exponential optical depth carried
across segments (docs/method.md section 8). Free flights and transmittance rules subclass it."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.instrument import count
from mitsuba_plugins.tracking.walk import MajorantSegments

VARIANT = mi.variant()


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
