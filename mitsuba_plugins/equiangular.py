"""Equiangular distance sampling toward point and spot lights (Kulla and Fajardo 2012,
"Importance Sampling Techniques for Path Tracing in Participating Media"), combined by
the balance heuristic with free-flight sampling (issue 29, experiment).

Along each path segment in a homogeneous medium of gray extinction, a second estimate
of the light scattered once toward the camera from a delta-position emitter: a point
``t`` of ``[0, t_end]`` is drawn with density proportional to the inverse squared
distance to the light, ``D / ((theta_b - theta_a) (D^2 + (t - Delta)^2))`` (``Delta``:
the ray parameter of the point closest to the light, ``D`` its distance), and the
light is sampled from there. The free-flight vertex's own emitter sample of the same
emitter estimates the same integral with density ``sigma_t exp(-sigma_t t)``: both are
weighted by the balance heuristic (the emitter's selection probability is the same in
both and cancels).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.contract import medium_interaction

#: Smallest distance from the ray to the light used in the pdf (a light on the ray's
#: line would give a delta-like density).
MIN_DISTANCE = 1e-6


class Segment:
    """The equiangular density over one segment ``[0, t_end]`` of ``ray`` toward the
    light at ``p``."""

    def __init__(self, ray: mi.Ray3f, t_end: mi.Float, p: mi.Point3f):
        self.delta = dr.dot(p - ray.o, ray.d)
        self.D = dr.maximum(dr.norm(p - ray(self.delta)), MIN_DISTANCE)
        self.theta_a = dr.atan2(-self.delta, self.D)
        self.theta_b = dr.atan2(dr.minimum(t_end, 1e30) - self.delta, self.D)

    def sample(self, u: mi.Float) -> mi.Float:
        theta = dr.lerp(self.theta_a, self.theta_b, u)
        return self.delta + self.D * dr.tan(theta)

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
    w = p_ff / (p_ff + p_eq)
    return dr.select(both & (p_ff + p_eq > 0), w, 1.0)


def gather(ctx, ray: mi.Ray3f, medium: mi.MediumPtr, t_end: mi.Float, beta: mi.Spectrum,
           shadow, active: mi.Bool):
    """The equiangular estimate along ``ray`` over ``[0, t_end]`` (times ``beta``, MIS
    weighted) on the ``active`` lanes, and the medium's (gray) extinction;
    ``shadow(ref, ds, medium, active)``: the transmittance to an emitter sample."""
    u_light = ctx.sampler.next_2d(active)
    u_t = ctx.sampler.next_1d(active)
    eligible = mi.Bool(active)
    origin = dr.zeros(mi.Interaction3f)
    origin.p, origin.time, origin.wavelengths = ray.o, ray.time, ray.wavelengths
    ds0, _ = ctx.emitters.sample_direction(origin, u_light, active, test_visibility=False)
    active &= is_point_light(ds0.emitter) & (ds0.pdf != 0)
    seg = Segment(ray, t_end, ds0.p)
    t = dr.clip(seg.sample(u_t), 0.0, t_end)
    p_eq = seg.pdf(t)
    mei = medium_interaction(ray, t)
    mei.medium = medium
    sigma_s, _, sigma_t = medium.get_scattering_coefficients(mei, eligible)
    sigma_t = mi.Spectrum(sigma_t)[0]
    p_ff = sigma_t * dr.exp(-sigma_t * t)
    active &= (p_eq > 0) & (t < t_end)
    ref = mi.Interaction3f(t, ray.time, ray.wavelengths, mei.p, mi.Normal3f(0.0))
    ds, em_weight = ctx.emitters.sample_direction(ref, u_light, active, test_visibility=False)
    phase_val, _ = medium.phase_function().eval_pdf(ctx.phase_ctx, mei, ds.d, active)
    T = shadow(ref, ds, medium, active)
    w = p_eq / (p_eq + p_ff)
    value = beta * mi.Spectrum(sigma_s) * (dr.exp(-sigma_t * t) * phase_val * w / p_eq) \
        * em_weight * T
    return dr.select(active, value, 0.0), sigma_t
