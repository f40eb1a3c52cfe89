"""Dwivedi sampling of random walks in dense homogeneous media (issue 29; docs/method.md
section 11): a zero-variance-based walk that is pulled back towards the surface it
entered through (Kriv\u00e1nek and d'Eon 2014, "A zero-variance-based sampling scheme for
Monte Carlo subsurface scattering"; Meng et al. 2016).

A path that enters a homogeneous medium through a surface remembers that surface's
outward normal ``n``. At each real collision in that medium the next direction comes,
with probability ``s`` (``volpath_delta``'s ``guiding``), from Dwivedi's density over
the cosine ``mu = <w, n>``

.. math::  p_D(\\mu) = \\frac{1}{\\ln\\frac{\\nu_0 + 1}{\\nu_0 - 1}}\\,\\frac{1}{\\nu_0 - \\mu}

(``nu_0``, the diffusion eigenvalue of the albedo, see :func:`eigenvalue`), and its
flight from the stretched exponential of rate ``sigma_t (1 - mu / nu_0)``: longer
steps towards the surface, shorter ones away from it. Otherwise (probability
``1 - s``) the direction comes from the phase function and the flight from
``sigma_t`` as usual. The weight is the phase function and transmittance over the
*mixture* of both joint (direction, distance) densities (one-sample MIS, balance
heuristic), so every path weight per vertex stays below ``1 / (1 - s)`` times the
unguided one, whatever the phase function's anisotropy. The weight is split in two:
at the vertex the phase function over the mixture of the two directional densities,
at the flight the ratio of the mixture of directional x distance densities to it
(:meth:`GuideState.flight_factor`). MIS with emitter sampling weighs directions
by the mixture's directional density (the transmittance being estimated by both
strategies, the weights only have to sum to one per direction).

Gray extinction only (a chromatic homogeneous medium's flights already weigh the
channels by spectral MIS); the walk is not replayed for gradients, so gradient renders
trace it unguided.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: Albedo range used for the eigenvalue: below, nu_0 is 1 to float precision (the
#: density is the uniform one's limit); above, nu_0 is kept finite.
ALBEDO_RANGE = (1e-3, 1.0 - 1e-6)
#: Upper bound of 1 / nu_0 (nu_0 > 1 keeps the density normalisable).
MAX_INV_EIGENVALUE = 1.0 - 1e-4


def eigenvalue(albedo: mi.Float) -> mi.Float:
    r"""The diffusion eigenvalue :math:`\nu_0 > 1` of an isotropic medium of single-
    scattering albedo ``albedo``: the root of :math:`\alpha \nu \operatorname{atanh}
    (1/\nu) = 1`. Newton's method on :math:`x = 1 / \nu` from the right of the root
    (:math:`\operatorname{atanh}(x)/x` is convex and increasing, so the iterates fall
    monotonically onto it), started at the diffusion limit :math:`\sqrt{3(1-\alpha)/
    \alpha}`, which is always above the root. Any :math:`\nu_0 > 1` keeps the sampling
    unbiased; its accuracy only matters for the variance."""
    a = dr.clip(albedo, *ALBEDO_RANGE)
    x = dr.minimum(dr.sqrt(3.0 * (1.0 - a) / a), MAX_INV_EIGENVALUE)
    for _ in range(4):
        at = dr.atanh(x)
        g = a * at / x - 1.0
        dg = a * (1.0 / (x * (1.0 - x * x)) - at / (x * x))
        x = dr.clip(x - g / dg, 1e-4, MAX_INV_EIGENVALUE)
    return dr.rcp(x)


def _log_ratio(nu0: mi.Float) -> mi.Float:
    return dr.log((nu0 + 1.0) / (nu0 - 1.0))


def dwivedi_pdf(nu0: mi.Float, mu: mi.Float) -> mi.Float:
    """Solid-angle density of Dwivedi's directions at cosine ``mu`` to the normal."""
    return dr.rcp(2.0 * dr.pi * _log_ratio(nu0) * (nu0 - mu))


def sample_dwivedi(nu0: mi.Float, normal: mi.Vector3f, u: mi.Point2f) -> mi.Vector3f:
    """A direction with density :func:`dwivedi_pdf` about ``normal`` (inverse CDF)."""
    mu = nu0 - (nu0 + 1.0) * dr.power((nu0 - 1.0) / (nu0 + 1.0), u.x)
    mu = dr.clip(mu, -1.0, 1.0)
    sin_theta = dr.safe_sqrt(1.0 - mu * mu)
    s, c = dr.sincos(2.0 * dr.pi * u.y)
    return mi.Frame3f(normal).to_world(mi.Vector3f(c * sin_theta, s * sin_theta, mu))


class GuideState:
    """Loop state of a guided walk. ``normal``: outward normal of the surface the path
    entered its homogeneous medium through; ``on``: the path is in that medium and
    guided. For the pending flight: ``rate``, the factor on ``sigma_t`` its distance is
    drawn with (1 unless Dwivedi's technique drew the direction); ``stretch``,
    ``1 - mu / nu_0`` of its direction; ``log_r``, ``log`` of the Dwivedi share of
    the directional mixture over the phase function's (``-inf``: unguided)."""
    DRJIT_STRUCT = {"normal": mi.Vector3f, "on": mi.Bool, "rate": mi.Float,
                    "stretch": mi.Float, "log_r": mi.Float}

    def __init__(self, normal=None, on=None, rate=None, stretch=None, log_r=None):
        self.normal, self.on, self.rate = normal, on, rate
        self.stretch, self.log_r = stretch, log_r

    @staticmethod
    def off() -> "GuideState":
        return GuideState(mi.Vector3f(0.0, 0.0, 1.0), mi.Bool(False), mi.Float(1.0),
                          mi.Float(1.0), mi.Float(-dr.inf))

    def flight_factor(self, sigma_t: mi.Float, t: mi.Float, scattered: mi.Bool) -> mi.Float:
        r"""The pending flight's weight over the unguided one: at a collision at ``t``
        :math:`(1 + r) / (1 + r\,a\,e^{\sigma_t (1 - a) t})`, at the end of the
        segment (``t`` its length) :math:`(1 + r) / (1 + r\,e^{\sigma_t (1 - a) t})`,
        ``a`` the stretch and ``r`` the directional mixture's Dwivedi share over the
        phase function's. 1 on unguided flights."""
        a = self.stretch
        exponent = self.log_r + sigma_t * (1.0 - a) * t + dr.select(scattered, dr.log(a), 0.0)
        factor = (1.0 + dr.exp(self.log_r)) / (1.0 + dr.exp(exponent))
        use = self.on & (self.log_r > -dr.inf)
        return dr.select(use, dr.select(dr.isnan(factor), 0.0, factor), 1.0)

    def consumed(self) -> "GuideState":
        """After a flight: the next one is unguided unless a vertex says otherwise."""
        return GuideState(self.normal, self.on, mi.Float(1.0), mi.Float(1.0),
                          mi.Float(-dr.inf))


class Guiding:
    """Dwivedi sampling at the vertices of one render (traced only where the scene has
    gray homogeneous media and ``probability`` > 0)."""

    def __init__(self, probability: float):
        self.s = float(probability)

    def enter(self, guide: GuideState, crossed: mi.Bool, si: mi.SurfaceInteraction3f,
              medium: mi.MediumPtr, d: mi.Vector3f) -> GuideState:
        """At surfaces the path crosses (``crossed``, its new ``medium`` and direction
        ``d`` set): guided from there on where it enters a homogeneous medium, about
        the surface's normal facing away from ``d``; unguided elsewhere."""
        entering = si.is_medium_transition() & (medium != None)  # noqa: E711
        on = dr.select(crossed, entering & medium.is_homogeneous(), guide.on)
        n = mi.Vector3f(si.n)
        normal = dr.select(crossed & on, dr.select(dr.dot(n, d) < 0, n, -n), guide.normal)
        return GuideState(normal, on, guide.rate, guide.stretch, guide.log_r)

    def mixture_pdf(self, guide: GuideState, nu0: mi.Float, phase_pdf: mi.Float,
                    d: mi.Vector3f) -> mi.Float:
        """Directional density of the mixture at ``d`` (the phase function's where
        unguided)."""
        mix = (1.0 - self.s) * phase_pdf + self.s * dwivedi_pdf(nu0, dr.dot(d, guide.normal))
        return dr.select(guide.on, mix, phase_pdf)

    def sample(self, guide: GuideState, phase, phase_ctx, mei, nu0: mi.Float,
               wo_phase: mi.Vector3f, phase_weight: mi.Spectrum, phase_pdf_s: mi.Float,
               u_technique: mi.Float, u2: mi.Point2f, active: mi.Bool):
        """The next direction at the medium vertices ``active``, given the phase
        function's sample (``wo_phase``, its weight and pdf, drawn from ``u2``):
        ``(wo, weight, pdf, guide)``. On guided lanes ``wo`` is Dwivedi's (probability
        ``s``, from ``u2`` too) or the phase function's, ``weight`` the phase function
        over the mixture's directional density ``pdf``, and ``guide`` holds the
        pending flight's terms; other lanes keep the phase function's sample."""
        guided = active & guide.on
        dwivedi = guided & (u_technique < self.s)
        wo = dr.select(dwivedi, sample_dwivedi(nu0, guide.normal, u2), wo_phase)
        value, pdf_phase = phase.eval_pdf(phase_ctx, mei, wo, guided)
        mu = dr.dot(wo, guide.normal)
        k_p = (1.0 - self.s) * pdf_phase
        k_d = self.s * dwivedi_pdf(nu0, mu)
        pdf = k_p + k_d
        weight = mi.Spectrum(value) * dr.select(pdf > 0, dr.rcp(pdf), 0.0)
        stretch = 1.0 - mu / nu0
        flight = GuideState(guide.normal, guide.on,
                            dr.select(dwivedi, stretch, guide.rate),
                            dr.select(guided, stretch, guide.stretch),
                            dr.select(guided, dr.log(k_d) - dr.log(k_p), guide.log_r))
        return (dr.select(guided, wo, wo_phase), dr.select(guided, weight, phase_weight),
                dr.select(guided, pdf, phase_pdf_s), flight)
