"""The media of a scene: what a render's kernel needs, per-medium dispatch, and
shadow-ray transmittance through media and index-matched surfaces."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins.contract import (diagonal, medium_interaction, probe_interaction,
                                      tracker_for)
from mitsuba_plugins.estimators import homogeneous_transmittance
from mitsuba_plugins.instrument import count

VARIANT = mi.variant()


def _is_chromatic(medium: mi.Medium) -> bool:
    """A homogeneous Mitsuba medium's extinction differs between channels, or, in
    spectral variants, between wavelengths anywhere in the visible range (they all
    claim spectral extinction by default; read back once per render)."""
    if not medium.has_spectral_extinction():
        return False
    _, _, sigma_t = medium.get_scattering_coefficients(probe_interaction())
    return bool(np.ptp(np.asarray(sigma_t).ravel()) > 0)


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
    plugin): which code a kernel needs, and per-medium dispatch.

    ``any``: the scene has media. ``homogeneous`` / ``heterogeneous``: some medium of
    that kind exists. ``chromatic_homogeneous`` / ``chromatic_heterogeneous``: some
    homogeneous / heterogeneous medium has chromatic extinction (channels differ).
    ``emission``: some medium emits.
    """

    def __init__(self, scene: mi.Scene):
        media = scene_media(scene)
        self.scene_extent = diagonal(scene.bbox())
        self.any = bool(media)
        homogeneous = [m for m in media if m.is_homogeneous()]
        self.trackers = {id(m): tracker_for(m, self.scene_extent, scene.bbox()) for m in media
                         if not m.is_homogeneous()}
        self.homogeneous = bool(homogeneous)
        self.heterogeneous = bool(self.trackers)
        multichannel = dr.size_v(mi.Spectrum) > 1
        self.chromatic_homogeneous = multichannel and any(_is_chromatic(m) for m in homogeneous)
        self.chromatic_heterogeneous = multichannel and any(
            t.is_chromatic for t in self.trackers.values())
        self.chromatic = self.chromatic_homogeneous or self.chromatic_heterogeneous
        self.emission = any(t.has_emission for t in self.trackers.values())

    def extent(self) -> float:
        """Longest stretch a ray can travel through one heterogeneous medium: the
        largest diagonal of their bounding boxes (the scene's, for media without one)."""
        sizes = [self.scene_extent if t.diagonal is None else t.diagonal
                 for t in self.trackers.values()]
        return max(sizes, default=0.0)

    def call(self, medium: mi.MediumPtr, fn, active):
        """``fn(tracker, mask)`` for each lane's heterogeneous medium; the caller keeps
        its own values where the mask is off.

        With several heterogeneous media each one's walk runs on its own lanes, one
        after the other (Dr.Jit 1.5 cannot compile these loops inside ``dr.dispatch``:
        "unhandled node kind call_input"); lanes of the other media leave at once.
        """
        trackers = list(self.trackers.values())
        if len(trackers) == 1:
            return fn(trackers[0], active)
        result = None
        for tracker in trackers:
            mine = active & (medium == mi.MediumPtr(tracker.medium))
            out = fn(tracker, mine)
            result = out if result is None else dr.select(mine, out, result)
        return result

    def dispatch(self, medium: mi.MediumPtr, active, value, homogeneous, heterogeneous):
        """The one homogeneous / heterogeneous split: ``value`` on lanes outside media,
        ``homogeneous(mask)`` on lanes in a homogeneous medium (traced only if the scene
        has one) and ``heterogeneous(tracker, mask)`` on the others."""
        in_medium = active & (medium != None)  # noqa: E711
        is_homogeneous = mi.Bool(False)
        if self.homogeneous:
            is_homogeneous = in_medium & medium.is_homogeneous()
            value = dr.select(is_homogeneous, homogeneous(is_homogeneous), value)
        if self.heterogeneous:
            mask = in_medium & ~is_homogeneous
            value = dr.select(mask, self.call(medium, heterogeneous, mask), value)
        return value

    def transmittance(self, medium: mi.MediumPtr, ray: mi.Ray3f, t_max: mi.Float,
                      sampler: mi.Sampler, estimator, active: mi.Bool) -> mi.Spectrum:
        """Transmittance over ``[0, t_max]`` of each lane's current medium: analytic in
        homogeneous media, ``estimator.transmittance(tracker, ray, t_max, sampler,
        mask)`` in heterogeneous ones (an entry of
        :data:`~mitsuba_plugins.estimators.TRANSMITTANCE_ESTIMATORS`, or a
        :class:`~mitsuba_plugins.marching.Marcher`)."""
        def analytic(mask):
            _, _, sigma_t = medium.get_scattering_coefficients(medium_interaction(ray, 0.0),
                                                               mask)
            return homogeneous_transmittance(mi.Spectrum(sigma_t), t_max)

        def estimated(tracker, mask):
            return estimator.transmittance(tracker, ray, t_max, sampler, mask)
        return self.dispatch(medium, active, mi.Spectrum(1.0), analytic, estimated)


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
    :mod:`mitsuba_plugins.replay`) says what happens on each, drawing from ``sampler``
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
