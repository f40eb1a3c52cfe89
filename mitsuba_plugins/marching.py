"""Ray marching through heterogeneous media (docs/method.md section 10).

A march cuts a ray's stretch of medium into cells and treats the medium as constant
in each cell, at its value at the cell's midpoint. Everything here is then *exact for
that piecewise-constant medium*: transmittance is ``exp(-sum sigma_t(mid) l)``, free
flights are drawn from its exponential pieces, and the light scattered once in a cell
is the closed-form integral of ``T(t) sigma_s`` over the cell. The only error is the
quadrature (midpoint) error of the optical depth, which shrinks with the step; it is
measured in ``benchmarks/volpath_raymarch.py``.

Cells (:class:`Marcher`):

* ``fixed``: boundaries at ``tmin + (u + k) dt`` for a jitter ``u`` drawn per march, so
  the first cell is ``u dt`` long and the grid of cells is different for each ray.
* ``majorant``: the majorant grid's segments (:class:`~mitsuba_plugins.majorant.MajorantGrid`)
  are cut into cells of ``dt = min(step_size, step_optical_depth / sigma_maj)``, so a
  cell's optical depth never exceeds ``step_optical_depth``; a segment whose majorant is
  0 (empty space) is one cell.

Step sizes are opaque Dr.Jit values: a new step size reuses the compiled kernel.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.majorant import DDAState
from mitsuba_plugins.tracking import (FreeFlight, MediumTracker, index_channel,
                                      medium_interaction, spectral_flight_weight)

VARIANT = mi.variant()

#: ``step_mode`` values of ``volpath_raymarch``.
STEP_MODES = ("fixed", "majorant")
#: A march stops once every channel's optical depth exceeds this (T < 1e-13): what lies
#: behind contributes less than float precision to anything in front.
TAU_CUTOFF = 30.0
#: Each cell is at least this fraction of its start parameter long, so a march always
#: moves on where ``t + dt`` rounds to ``t`` (steps far below float resolution).
MIN_RELATIVE_STEP = 2.0 ** -20


def exp_integral(x):
    """``(1 - exp(-x)) / x`` for ``x >= 0`` (1 at 0, 0 at infinity): the mean of
    ``exp(-x s)`` over ``s`` in [0, 1]. A Taylor series below 0.05 (truncation error
    < 1e-9), where the quotient would cancel in single precision."""
    small = x < 0.05
    series = 1.0 - x * (1 / 2 - x * (1 / 6 - x * (1 / 24 - x * (1 / 120))))
    return dr.select(small, series, (1.0 - dr.exp(-x)) / dr.select(small, 1.0, x))


def cell_integral(sigma_t, length):
    """``int_0^length exp(-sigma_t s) ds`` (``1 / sigma_t`` for an infinite length)."""
    x = sigma_t * length
    return dr.select(dr.isinf(length) & (sigma_t > 0), dr.rcp(sigma_t),
                     length * exp_integral(x))


def _log1p(y):
    """``log(1 + y)`` without cancellation (Goldberg's trick: the rounding of ``1 + y``
    is undone by ``y / (u - 1)``)."""
    u = 1.0 + y
    return dr.select(u == 1.0, y, dr.log(u) * y / dr.select(u == 1.0, 1.0, u - 1.0))


def sample_cell_point(sigma_t: mi.Spectrum, length: mi.Float, u: mi.Float, spectral: bool):
    r"""A point ``s`` in a cell ``[0, length]`` of constant extinction for the in-scattering
    integral ``int_0^length T(s) g(s) ds``, and its weight ``T(s) / q(s)`` (per channel,
    ``T`` relative to the cell's start).

    Gray: ``q`` is the truncated exponential ``sigma_t e^{-sigma_t s} / (1 - e^{-sigma_t l})``
    and the weight is the constant ``cell_integral(sigma_t, l)``: the estimator is exact
    when ``g`` is constant. Chromatic (``spectral``): a channel is picked uniformly (from
    ``u``, which is then reused) and ``q`` is the mean of the channels' truncated
    exponentials (one-sample MIS, balance heuristic), so every weight is at most 3x that
    channel's own cell integral, whatever the extinction ratio.
    """
    n = dr.size_v(mi.Spectrum)
    if spectral:
        channel = mi.UInt32(dr.minimum(u * n, n - 1))
        u = u * n - mi.Float(channel)
        sigma = index_channel(sigma_t, channel)
    else:
        sigma = sigma_t[0]
    x = sigma * length
    # mass of the truncated exponential, 1 - exp(-x), accurate for small x
    a = dr.select(x < 1.0, x * exp_integral(x), 1.0 - dr.exp(-x))
    s = dr.select(x < 1e-6, u * length, -_log1p(-u * a) / dr.select(sigma > 0, sigma, 1.0))
    s = dr.minimum(dr.select(dr.isfinite(s), s, 0.0), length)
    if not spectral:
        return s, mi.Spectrum(cell_integral(sigma, length))
    # q(s) = mean_c exp(-sigma_c s) / I_c with I_c the cell integral; exponents are
    # shifted by the smallest so a dense channel does not make 0/0.
    exponent = sigma_t * s
    rel = dr.exp(dr.min(exponent) - exponent)
    q = dr.mean(rel / cell_integral(sigma_t, length))
    return s, mi.Spectrum(rel / q)


class FixedMarch:
    """Loop state of a fixed-step march."""
    DRJIT_STRUCT = {"t": mi.Float,          # start of the next cell
                    "t_end": mi.Float,      # end of the march
                    "boundary": mi.Float}   # next cell boundary of the jittered grid

    def __init__(self, t=None, t_end=None, boundary=None):
        self.t, self.t_end, self.boundary = t, t_end, boundary


class MajorantMarch:
    """Loop state of a march whose steps follow the majorant grid."""
    DRJIT_STRUCT = {"t": mi.Float,          # start of the next cell
                    "t_end": mi.Float,      # end of the march
                    "boundary": mi.Float,   # next cell boundary in this segment
                    "seg_end": mi.Float,    # end of the current majorant segment
                    "dt": mi.Float,         # step in this segment
                    "u": mi.Float,          # jitter of the cell grid
                    "dda": DDAState}        # walk through the majorant grid

    def __init__(self, t=None, t_end=None, boundary=None, seg_end=None, dt=None, u=None,
                 dda=None):
        self.t, self.t_end, self.boundary, self.seg_end = t, t_end, boundary, seg_end
        self.dt, self.u, self.dda = dt, u, dda


class Marcher:
    """How a march cuts rays into cells: ``mode`` in :data:`STEP_MODES`, ``step_size``
    in world units, ``step_optical_depth`` (``majorant`` mode) in mean free paths of
    the cell majorant. Built per render; the step values are opaque."""

    def __init__(self, mode: str, step_size: float, step_optical_depth: float):
        self.mode = mode
        self.step_size = dr.opaque(mi.Float, step_size)
        self.step_optical_depth = dr.opaque(mi.Float, step_optical_depth)

    def start(self, tracker: MediumTracker, ray: mi.Ray3f, tmin, tmax, u: mi.Float, active):
        """State for marching ``ray`` over ``[tmin, tmax]`` with jitter ``u`` in [0, 1)."""
        if self.mode == "fixed":
            return FixedMarch(mi.Float(tmin), mi.Float(tmax), tmin + u * self.step_size)
        dda = tracker.grid.start(ray, tmin, tmax, active)
        return MajorantMarch(mi.Float(tmin), mi.Float(tmax), mi.Float(tmin), mi.Float(tmin),
                             mi.Float(0.0), mi.Float(u), dda)

    def next(self, tracker: MediumTracker, state, active):
        """The next cell ``(t0, t1, state)``; call while ``t1 < t_end`` of the last one."""
        t0 = mi.Float(state.t)
        if self.mode == "fixed":
            dt = self.step_size
            boundary = state.boundary
        else:
            fetch = active & (t0 >= state.seg_end)
            _, seg_end, sigma_maj, _, dda = tracker.grid.next_bounds(state.dda, fetch,
                                                                     minorant=False)
            empty = sigma_maj <= 0
            dt_new = dr.minimum(self.step_size,
                                self.step_optical_depth / dr.select(empty, 1.0, sigma_maj))
            state.dda = dda
            state.seg_end = dr.select(fetch, seg_end, state.seg_end)
            state.dt = dr.select(fetch, dr.select(empty, dr.inf, dt_new), state.dt)
            boundary = dr.select(fetch, dr.select(empty, state.seg_end, t0 + state.u * dt_new),
                                 state.boundary)
            dt = state.dt
        end = state.t_end if self.mode == "fixed" else state.seg_end
        t1 = dr.minimum(boundary, end)
        t1 = dr.minimum(dr.maximum(t1, t0 + t0 * MIN_RELATIVE_STEP), end)
        state.boundary = dr.select(active & (t1 >= boundary), boundary + dt, boundary)
        state.t = dr.select(active, t1, t0)
        return t0, t1, state

    @dr.syntax
    def transmittance(self, tracker: MediumTracker, ray: mi.Ray3f, t_max: mi.Float,
                      sampler: mi.Sampler, active: mi.Bool) -> mi.Spectrum:
        """Marched transmittance ``exp(-sum sigma_t(mid) l)`` over ``[0, t_max]``: exact
        for the piecewise-constant medium; one random number (the jitter)."""
        tmin, tmax = tracker.bounds(ray, t_max)
        state = self.start(tracker, ray, tmin, tmax, sampler.next_1d(active), active)

        # ------------------------------ loop state ------------------------------
        tau = mi.Spectrum(0.0)                          # optical depth so far
        active = mi.Bool(active) & (tmin < tmax)

        while dr.hint(active, label="march_transmittance"):
            t0, t1, state = self.next(tracker, state, active)
            sigma_t = tracker.sigma_t(medium_interaction(ray, 0.5 * (t0 + t1)), active)
            tau[active] += sigma_t * (t1 - t0)
            active &= (t1 < tmax) & (dr.min(tau) < TAU_CUTOFF)
        return dr.exp(-tau)

    def __repr__(self):
        return (f"{self.mode} (step_size {self.step_size[0]:g}"
                + (f", step_optical_depth {self.step_optical_depth[0]:g})"
                   if self.mode == "majorant" else ")"))


@dr.syntax
def march_flight(tracker: MediumTracker, ray: mi.Ray3f, t_max: mi.Float, sampler: mi.Sampler,
                 beta: mi.Spectrum, r_u: mi.Spectrum, hero: mi.UInt32, spectral: bool,
                 emission: bool, marcher: Marcher, active: mi.Bool) -> FreeFlight:
    r"""Sample the next collision along ``ray`` in the marched (piecewise-constant) medium.

    One exponential optical depth is drawn and spent cell by cell, so a cell of optical
    depth ``tau_i`` holds the collision with probability ``1 - exp(-tau_i)`` given the
    flight reached it, at the exact position within it: free-flight sampling of the
    piecewise-constant medium, with no null collisions. At a collision the throughput
    takes the albedo ``sigma_s / sigma_t`` (absorption as a weight rather than a coin
    flip: same expectation, less variance). Chromatic extinction: the hero channel's
    optical depth decides and :func:`~mitsuba_plugins.tracking.spectral_flight_weight`
    weights the path over channels, as in homogeneous media.

    With ``emission`` the medium's emission is collected at the collision (``beta
    sigma_a Le / sigma_t``, whose expectation is ``int T sigma_a Le dt``).
    """
    tmin, tmax = tracker.bounds(ray, t_max)
    state = marcher.start(tracker, ray, tmin, tmax, sampler.next_1d(active), active)
    entered = mi.Bool(active) & (tmin < tmax)

    # ------------------------------ loop state ------------------------------
    tau_left = -dr.log(1.0 - sampler.next_1d(entered))  # hero optical depth to the collision
    tau = mi.Spectrum(0.0)                               # optical depth so far (chromatic only)
    t = mi.Float(tmin)                                   # position reached
    sigma_t_c = mi.Spectrum(0.0)                         # extinction at the collision
    sigma_s_c = mi.Spectrum(0.0)                         # scattering at the collision
    Le_c = mi.Spectrum(0.0)                              # emission at the collision
    scattered = mi.Bool(False)                           # collided in the medium
    active = mi.Bool(entered)

    while dr.hint(active, label="march_flight"):
        t0, t1, state = marcher.next(tracker, state, active)
        sigma_t, sigma_s, Le = tracker.coefficients(
            medium_interaction(ray, 0.5 * (t0 + t1)), active)
        sigma_h = sigma_t[0]
        if dr.hint(spectral, mode="scalar"):
            sigma_h = index_channel(sigma_t, hero)
        cell_tau = sigma_h * (t1 - t0)
        collide = active & (tau_left < cell_tau)
        d = dr.select(collide, tau_left / dr.select(collide, sigma_h, 1.0), t1 - t0)
        t[active] = t0 + d
        if dr.hint(spectral, mode="scalar"):
            tau[active] += sigma_t * d
        tau_left[active & ~collide] = tau_left - cell_tau
        sigma_t_c[collide] = sigma_t
        sigma_s_c[collide] = sigma_s
        if dr.hint(emission, mode="scalar"):
            Le_c[collide] = Le
        scattered |= collide
        active &= ~collide & (t1 < tmax)

    if dr.hint(spectral, mode="scalar"):
        weight, r_u_new = spectral_flight_weight(tau, sigma_t_c, scattered, r_u)
        r_u = dr.select(entered, r_u_new, r_u)
    else:
        weight = mi.Spectrum(dr.select(scattered,
                                       dr.rcp(dr.select(scattered, sigma_t_c[0], 1.0)), 1.0))
    beta_flight = dr.select(entered, beta * weight, beta)
    L_e = mi.Spectrum(0.0)
    if dr.hint(emission, mode="scalar"):
        L_e = dr.select(scattered, beta_flight * (sigma_t_c - sigma_s_c) * Le_c, 0.0)
    beta = dr.select(scattered, beta_flight * sigma_s_c, beta_flight)
    return FreeFlight(scattered, t, beta, r_u, L_e)


@dr.syntax
def march_single(tracker: MediumTracker, ray: mi.Ray3f, t_max: mi.Float, sampler: mi.Sampler,
                 beta: mi.Spectrum, r_u: mi.Spectrum, in_scatter, spectral: bool,
                 emission: bool, marcher: Marcher, nee: mi.Bool, active: mi.Bool) -> FreeFlight:
    r"""Single scattering along ``ray`` over ``[0, t_max]`` in the marched medium.

    Per cell of length ``l`` with midpoint coefficients, the light scattered once
    towards the ray, :math:`\int_{cell} T(t)\, \sigma_s\, L_s(t)\, dt`, is estimated with
    one point from :func:`sample_cell_point` and ``in_scatter(medium, mei, active)``,
    an estimate of :math:`L_s` (one emitter sample with its phase function value,
    emitter pdf and shadow transmittance). The classic Riemann sum
    ``T sigma_s L_s dt`` is not used: with ``sigma_t dt > 1`` it scatters more light
    than enters the cell; the cell integral never does. With ``emission``, each cell
    adds ``T(t0) sigma_a Le`` times its cell integral.

    Returns a :class:`~mitsuba_plugins.tracking.FreeFlight` that never scatters:
    ``beta`` times the marched transmittance, and ``L_e``, the radiance gathered
    (already times ``beta``). ``nee`` masks lanes allowed an emitter sample (depth).
    """
    tmin, tmax = tracker.bounds(ray, t_max)
    state = marcher.start(tracker, ray, tmin, tmax, sampler.next_1d(active), active)
    medium = mi.MediumPtr(tracker.medium)

    # ------------------------------ loop state ------------------------------
    tau = mi.Spectrum(0.0)                              # optical depth so far
    L = mi.Spectrum(0.0)                                # light gathered (per unit beta)
    active = mi.Bool(active) & (tmin < tmax)

    while dr.hint(active, label="march_single"):
        t0, t1, state = marcher.next(tracker, state, active)
        length = t1 - t0
        sigma_t, sigma_s, Le = tracker.coefficients(
            medium_interaction(ray, 0.5 * (t0 + t1)), active)
        T0 = dr.exp(-tau)

        # --------------- one emitter sample from a point in the cell ---------------
        s, weight = sample_cell_point(sigma_t, length, sampler.next_1d(active), spectral)
        lit = active & nee & dr.any(sigma_s > 0)
        mei = medium_interaction(ray, t0 + s)
        mei.medium = medium
        L[lit] += T0 * weight * sigma_s * in_scatter(medium, mei, lit)
        if dr.hint(emission, mode="scalar"):
            L[active] += T0 * (sigma_t - sigma_s) * Le * cell_integral(sigma_t, length)

        tau[active] += sigma_t * length
        active &= (t1 < tmax) & (dr.min(tau) < TAU_CUTOFF)

    return FreeFlight(mi.Bool(False), mi.Float(tmax), beta * dr.exp(-tau), r_u, beta * L)
