"""Equiangular distance sampling toward point and spot lights (Kulla and Fajardo 2012,
"Importance Sampling Techniques for Path Tracing in Participating Media"), combined by
the balance heuristic with free-flight sampling: ``volpath_delta``'s ``equiangular``
(docs/method.md section 12).

Along each path segment ``[0, t_end]`` in a homogeneous medium of gray extinction, the
light scattered once at the segment is estimated twice:

* at the free-flight vertex (if the flight collides), by its emitter sample, ``t`` drawn
  with density ``sigma_t exp(-sigma_t t)``;
* here: an emitter is selected as next-event estimation selects one; if it is a point or
  spot light (position ``p``), ``t`` is drawn with density proportional to the inverse
  squared distance to it, ``D / ((theta_b - theta_a) (D^2 + (t - Delta)^2))``
  (``Delta``: the ray parameter of the point closest to ``p``, ``D`` its distance,
  ``theta`` the angle seen from ``p``), and the light is sampled from ``ray(t)``.

Both are weighted by the balance heuristic over the two densities of ``t`` (the
emitter's selection probability is the same in both and cancels); emitters without a
position (area, environment, directional) are left to the vertex alone. This pays where
free flights seldom collide near the light: a light inside a thin medium. Where the
lights are outside a dense medium the equiangular point falls deep inside, its weight
and contribution are ~0, and only its cost remains (docs/benchmarks.md).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.instrument import settings
from mitsuba_plugins.tracking.shadow_rays import shadow_transmittance
from mitsuba_plugins.tracking.trackers import medium_interaction

#: Smallest distance from the ray to the light used in the density (a light on the
#: ray's line would give a delta-like density).
MIN_DISTANCE = 1e-6


def traced(integrator, scene: mi.Scene, media) -> bool:
    """Whether this render traces equiangular sampling: asked for, next-event estimation
    on, and the scene has a homogeneous medium and a point or spot light. Homogeneous
    media of chromatic extinction are not supported (their flights are weighted over
    channels, docs/method.md section 7): there it is off, with a warning."""
    if not getattr(integrator, "equiangular", False) or "nee" not in settings.terms:
        return False
    if not media.homogeneous or not any(
            mi.has_flag(e.flags(), mi.EmitterFlags.DeltaPosition) for e in scene.emitters()):
        return False
    if media.chromatic_homogeneous:
        mi.Log(mi.LogLevel.Warn, "volpath_delta: equiangular is off in this scene: it "
               "supports homogeneous media of gray extinction only")
        return False
    return True


class Segment:
    """The equiangular density over a segment ``[0, t_end]`` of ``ray`` (unit direction)
    toward the light at ``p``."""

    def __init__(self, ray: mi.Ray3f, t_end: mi.Float, p: mi.Point3f):
        self.delta = dr.dot(p - ray.o, ray.d)
        self.D = dr.maximum(dr.norm(p - ray(self.delta)), MIN_DISTANCE)
        self.theta_a = dr.atan2(-self.delta, self.D)
        self.theta_b = dr.atan2(dr.minimum(t_end, 1e30) - self.delta, self.D)

    def sample(self, u: mi.Float) -> mi.Float:
        return self.delta + self.D * dr.tan(dr.lerp(self.theta_a, self.theta_b, u))

    def pdf(self, t: mi.Float) -> mi.Float:
        span = self.theta_b - self.theta_a
        pdf = self.D / (span * (dr.square(self.D) + dr.square(t - self.delta)))
        return dr.select(span > 0, pdf, 0.0)


def is_point_light(emitter: mi.EmitterPtr) -> mi.Bool:
    return mi.has_flag(emitter.flags(), mi.EmitterFlags.DeltaPosition)


def free_flight_weight(ray: mi.Ray3f, t_end: mi.Float, sigma_t: mi.Float, t: mi.Float,
                       ds: mi.DirectionSample3f, eligible: mi.Bool) -> mi.Float:
    """Balance-heuristic weight of the emitter sample ``ds`` taken at the free-flight
    vertex ``ray(t)`` (1 where equiangular sampling could not have drawn it)."""
    both = eligible & is_point_light(ds.emitter)
    p_ff = sigma_t * dr.exp(-sigma_t * t)
    p_eq = Segment(ray, t_end, ds.p).pdf(t)
    return dr.select(both & (p_ff + p_eq > 0), p_ff / (p_ff + p_eq), 1.0)


def gather(ctx, ray: mi.Ray3f, medium: mi.MediumPtr, t_end: mi.Float, beta: mi.Spectrum,
           roulette: float, eligible: mi.Bool):
    """The equiangular estimate along ``ray`` over ``[0, t_end]`` (times ``beta``, MIS
    weighted) on the ``eligible`` lanes, and the medium's (gray) extinction on all of
    them, which :func:`free_flight_weight` needs whichever emitter a lane selects here.
    ``roulette``: the shadow ray's threshold."""
    u_light = ctx.sampler.next_2d(eligible)
    u_t = ctx.sampler.next_1d(eligible)
    origin = dr.zeros(mi.Interaction3f)
    origin.p, origin.time, origin.wavelengths = ray.o, ray.time, ray.wavelengths
    light, _ = ctx.emitters.sample_direction(origin, u_light, eligible, test_visibility=False)
    seg = Segment(ray, t_end, light.p)
    t = dr.clip(seg.sample(u_t), 0.0, t_end)
    p_eq = seg.pdf(t)
    # a new mask, never the caller's narrowed in place: the vertex is weighed on every
    # eligible lane
    active = eligible & is_point_light(light.emitter) & (light.pdf != 0) & (p_eq > 0) \
        & (t < t_end)

    mei = medium_interaction(ray, t)
    mei.medium = medium
    sigma_s, _, sigma_t = medium.get_scattering_coefficients(mei, eligible)
    sigma_t = mi.Spectrum(sigma_t)[0]
    ref = mi.Interaction3f(t, ray.time, ray.wavelengths, mei.p, mi.Normal3f(0.0))
    # the same numbers select the same emitter, whose position does not depend on ref
    ds, em_weight = ctx.emitters.sample_direction(ref, u_light, active, test_visibility=False)
    phase_val, _ = medium.phase_function().eval_pdf(ctx.phase_ctx, mei, ds.d, active)
    T = shadow_transmittance(ctx.scene, ctx.media, ref, ds, medium, ctx.sampler, ctx.estimator,
                             active, roulette)
    attenuation = dr.exp(-sigma_t * t)
    value = beta * mi.Spectrum(sigma_s) * (attenuation * phase_val
                                           / (p_eq + sigma_t * attenuation)) * em_weight * T
    return dr.select(active, value, 0.0), sigma_t
