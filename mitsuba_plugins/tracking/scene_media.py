"""The media of a scene: what a render's kernel needs (:class:`SceneMedia`, trace-time
specialisation) and the one homogeneous/heterogeneous dispatch per medium."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins.tracking.homogeneous import homogeneous_transmittance
from mitsuba_plugins.tracking.trackers import (diagonal, medium_interaction,
                                               probe_interaction, tracker_for)

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
        :data:`~mitsuba_plugins.tracking.transmittance.TRANSMITTANCE_ESTIMATORS`, or a
        :class:`~mitsuba_plugins.tracking.marching.Marcher`)."""
        def analytic(mask):
            _, _, sigma_t = medium.get_scattering_coefficients(medium_interaction(ray, 0.0),
                                                               mask)
            return homogeneous_transmittance(mi.Spectrum(sigma_t), t_max)

        def estimated(tracker, mask):
            return estimator.transmittance(tracker, ray, t_max, sampler, mask)
        return self.dispatch(medium, active, mi.Spectrum(1.0), analytic, estimated)


