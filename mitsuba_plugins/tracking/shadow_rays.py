"""Shadow rays through media: transmittance piece by piece from a vertex to a light, through
media and index-matched (``null``) surfaces, with Russian roulette between pieces
(:class:`TransmittancePass`)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.instrument import count
from mitsuba_plugins.tracking.scene_media import SceneMedia


def shadow_transmittance(scene: mi.Scene, media: SceneMedia, ref: mi.Interaction3f,
                         ds: mi.DirectionSample3f, medium: mi.MediumPtr, sampler: mi.Sampler,
                         estimator, active: mi.Bool, roulette: float = 0.0) -> mi.Spectrum:
    """Transmittance from ``ref`` to the emitter sample ``ds`` through media and
    index-matched (``null``) surfaces; any other surface blocks (as in Mitsuba's
    ``volpath``, a surface passes ``eval_null_transmission``). ``roulette``: the
    threshold of :meth:`TransmittancePass.roulette` between pieces (0: none)."""
    return shadow_pieces(scene, ref, ds, medium, TransmittancePass(media, estimator, roulette),
                         sampler, active)


class TransmittancePass:
    """What :func:`shadow_pieces` does on a shadow ray's pieces: multiply the
    transmittance estimates (``value``, from 1) and the null surfaces' transmission;
    stops where it is 0; Russian roulette between pieces below ``threshold``
    (:meth:`roulette`)."""

    def __init__(self, media, estimator, threshold: float = 0.0):
        self.media, self.estimator, self.threshold = media, estimator, threshold

    def initial(self):
        return mi.Spectrum(1.0)

    def piece(self, value, medium, ray, t_piece, sampler, active):
        value[active] *= self.media.transmittance(medium, ray, t_piece, sampler,
                                                  self.estimator, active)
        return value

    def surface(self, value, si, bsdf, hit):
        value[hit] *= bsdf.eval_null_transmission(si, hit)
        return value

    def goes_on(self, value):
        return dr.any(value != 0)

    def roulette(self, value, sampler, going_on):
        """Between pieces, on lanes ``going_on`` to another: where ``max(value)`` is
        below the threshold, go on with probability ``q = max(value) / threshold``
        and ``value / q`` (then ``max(value)`` = threshold), else 0. Unbiased; each
        piece it ends saves an intersection and a transmittance estimate, which in
        dense media are most of a shadow ray's cost (issue 29)."""
        if self.threshold <= 0:
            return value
        v = dr.max(value)
        play = going_on & (v > 0) & (v < self.threshold)
        q = v / self.threshold
        dies = sampler.next_1d(play) >= q
        return dr.select(play, dr.select(dies, 0.0, value / q), value)


@dr.syntax
def shadow_pieces(scene: mi.Scene, ref: mi.Interaction3f, ds: mi.DirectionSample3f,
                  medium: mi.MediumPtr, what, sampler, active: mi.Bool):
    """The pieces of the shadow ray from ``ref`` to ``ds``, medium by medium through
    index-matched surfaces: ``what`` (:class:`TransmittancePass`, or the gradient pass of
    :mod:`mitsuba_plugins.tracking.replay`) says what happens on each, drawing from ``sampler``
    (an argument, so that the loop carries its state); returns its value."""
    # ------------------------------ loop state ------------------------------
    ray = ref.spawn_ray(ds.d)                                 # current shadow-ray piece
    remaining = ds.dist * (1.0 - mi.math.ShadowEpsilon)       # distance left to the emitter
    value = what.initial()                                    # e.g. transmittance so far
    medium = mi.MediumPtr(medium)                             # medium of the current piece
    active = mi.Bool(active)

    while dr.hint(active, label="shadow_ray"):
        ray.maxt = remaining
        si = scene.ray_intersect(ray, mi.RayFlags.All, False, active)
        count("intersections", active)
        value = what.piece(value, medium, ray, dr.minimum(si.t, remaining), sampler, active)
        hit = active & si.is_valid()
        bsdf = si.bsdf(ray)
        value = what.surface(value, si, bsdf, hit)
        medium[hit & si.is_medium_transition()] = si.target_medium(ray.d)
        remaining[hit] = remaining - si.t
        ray[hit] = si.spawn_ray(ray.d)
        value = what.roulette(value, sampler, hit & (remaining > 0))
        active = hit & what.goes_on(value) & (remaining > 0)
    return value
