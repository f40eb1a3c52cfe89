"""Ray marching through heterogeneous media (docs/method.md section 10).

A march cuts a ray's stretch of medium into cells and treats the medium as constant
in each cell, at its value at the cell's midpoint. Everything here is then *exact for
that piecewise-constant medium*: transmittance is ``exp(-sum sigma_t(mid) l)``, free
flights are drawn from its exponential pieces, and the light scattered once in a cell
is the closed-form integral of ``T(t) sigma_s`` over the cell. The only error is the
quadrature (midpoint) error of the optical depth, which shrinks with the step; it is
measured in ``benchmarks/volpath_raymarch.py``.

A march is the one walk (:func:`mitsuba_plugins.tracking.walk.walk`) with a cell iterator as
its segments and a rule that treats each cell whole: :class:`MarchedTransmittance`,
:class:`MarchedFlight` and :class:`MarchedSingle`.

Cells (:class:`Marcher`):

* ``fixed``: boundaries at ``t_in + (u + k) dt`` for a jitter ``u`` drawn per march, so
  the first cell is ``u dt`` long and the grid of cells is different for each ray.
* ``majorant``: the majorant grid's segments (:class:`~mitsuba_plugins.tracking.majorant_grid.MajorantGrid`)
  are cut into cells of ``dt = min(step_size, step_optical_depth / sigma_maj)``, so a
  cell's optical depth never exceeds ``step_optical_depth``; a segment whose majorant is
  0 (empty space) is one cell.

Step sizes are opaque Dr.Jit values: a new step size reuses the compiled kernel.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.tracking.homogeneous import FreeFlight, spectral_flight_weight
from mitsuba_plugins.tracking.majorant_grid import DDAState
from mitsuba_plugins.tracking.trackers import Tracker, index_channel, medium_interaction
from mitsuba_plugins.tracking.walk import walk

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


def sample_cell_point(sigma_t: mi.Spectrum, length: mi.Float, u: mi.Float, chromatic: bool):
    r"""A point ``s`` in a cell ``[0, length]`` of constant extinction for the in-scattering
    integral ``int_0^length T(s) g(s) ds``, and its weight ``T(s) / q(s)`` (per channel,
    ``T`` relative to the cell's start).

    Gray: ``q`` is the truncated exponential ``sigma_t e^{-sigma_t s} / (1 - e^{-sigma_t l})``
    and the weight is the constant ``cell_integral(sigma_t, l)``: the estimator is exact
    when ``g`` is constant. ``chromatic``: a channel is picked uniformly (from
    ``u``, which is then reused) and ``q`` is the mean of the channels' truncated
    exponentials (one-sample MIS, balance heuristic), so every weight is at most 3x that
    channel's own cell integral, whatever the extinction ratio.
    """
    n = dr.size_v(mi.Spectrum)
    if chromatic:
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
    if not chromatic:
        return s, mi.Spectrum(cell_integral(sigma, length))
    # q(s) = mean_c exp(-sigma_c s) / I_c with I_c the cell integral; exponents are
    # shifted by the smallest so a dense channel does not make 0/0.
    exponent = sigma_t * s
    rel = dr.exp(dr.min(exponent) - exponent)
    q = dr.mean(rel / cell_integral(sigma_t, length))
    return s, mi.Spectrum(rel / q)


# -- cell iterators ------------------------------------------------------------------
class FixedCellState:
    """State of :class:`FixedCells`."""
    DRJIT_STRUCT = {"t_end": mi.Float,      # end of the current cell
                    "t_stop": mi.Float,     # end of the march
                    "boundary": mi.Float}   # next cell boundary of the jittered grid

    def __init__(self, t_end=None, t_stop=None, boundary=None):
        self.t_end, self.t_stop, self.boundary = t_end, t_stop, boundary


class MajorantCellState:
    """State of :class:`MajorantCells`."""
    DRJIT_STRUCT = {"t_end": mi.Float,      # end of the current cell
                    "boundary": mi.Float,   # next cell boundary in this segment
                    "t_cell": mi.Float,    # end of the current majorant segment
                    "dt": mi.Float,         # step in this segment
                    "u": mi.Float,          # jitter of the cell grid
                    "dda": DDAState}        # walk through the majorant grid

    def __init__(self, t_end=None, boundary=None, t_cell=None, dt=None, u=None, dda=None):
        self.t_end, self.boundary, self.t_cell = t_end, boundary, t_cell
        self.dt, self.u, self.dda = dt, u, dda


def _cell_end(t0, boundary, end):
    """End of the cell starting at ``t0``: the next boundary, at least a relative
    :data:`MIN_RELATIVE_STEP` on, never past ``end``."""
    t1 = dr.minimum(boundary, end)
    return dr.minimum(dr.maximum(t1, t0 + t0 * MIN_RELATIVE_STEP), end)


class FixedCells:
    """Cell iterator of ``fixed`` marches: boundaries at ``t_in + (u + k) step_size``."""

    def __init__(self, step_size: mi.Float):
        self.step_size = step_size

    def start(self, tracker, ray, t_in, t_out, sampler, active):
        return self.start_at(tracker, ray, t_in, t_out, sampler.next_1d(active), active)

    def start_at(self, tracker, ray, t_in, t_out, u, active):
        """State with jitter ``u`` in [0, 1)."""
        return FixedCellState(mi.Float(t_in), mi.Float(t_out), t_in + u * self.step_size)

    def next(self, tracker, ray, state, t, active):
        """The cell ``[t, state.t_end]`` that follows position ``t``: ``(active, state)``."""
        t1 = _cell_end(t, state.boundary, state.t_stop)
        boundary = dr.select(active & (t1 >= state.boundary), state.boundary + self.step_size,
                             state.boundary)
        return active, FixedCellState(dr.select(active, t1, state.t_end), state.t_stop, boundary)


class MajorantCells:
    """Cell iterator of ``majorant`` marches: each majorant segment cut into cells of
    ``min(step_size, step_optical_depth / sigma_maj)``; an empty one is one cell."""

    def __init__(self, step_size: mi.Float, step_optical_depth: mi.Float):
        self.step_size, self.step_optical_depth = step_size, step_optical_depth

    def start(self, tracker, ray, t_in, t_out, sampler, active):
        return self.start_at(tracker, ray, t_in, t_out, sampler.next_1d(active), active)

    def start_at(self, tracker, ray, t_in, t_out, u, active):
        dda = tracker.march_grid.start(ray, t_in, t_out, active)
        return MajorantCellState(mi.Float(t_in), mi.Float(t_in), mi.Float(t_in), mi.Float(0.0),
                                 mi.Float(u), dda)

    def next(self, tracker, ray, state, t, active):
        fetch = active & (t >= state.t_cell)
        _, t_cell, sigma_maj, _, dda = tracker.march_grid.next_bounds(state.dda, fetch,
                                                                       minorant=False)
        empty = sigma_maj <= 0
        dt_new = dr.minimum(self.step_size,
                            self.step_optical_depth / dr.select(empty, 1.0, sigma_maj))
        t_cell = dr.select(fetch, t_cell, state.t_cell)
        dt = dr.select(fetch, dr.select(empty, dr.inf, dt_new), state.dt)
        boundary = dr.select(fetch, dr.select(empty, t_cell, t + state.u * dt_new),
                             state.boundary)
        t1 = _cell_end(t, boundary, t_cell)
        boundary = dr.select(active & (t1 >= boundary), boundary + dt, boundary)
        return active, MajorantCellState(dr.select(active, t1, state.t_end), boundary, t_cell,
                                         dt, state.u, dda)


class Marcher:
    """How a march cuts rays into cells: ``mode`` in :data:`STEP_MODES`, ``step_size``
    in world units, ``step_optical_depth`` (``majorant`` mode) in mean free paths of
    the cell majorant. Built per render; the step values are opaque. A transmittance
    estimator like those of :data:`mitsuba_plugins.tracking.transmittance.TRANSMITTANCE_ESTIMATORS`."""

    def __init__(self, mode: str, step_size: float, step_optical_depth: float):
        self.mode = mode
        self.step_size = dr.opaque(mi.Float, step_size)
        self.step_optical_depth = dr.opaque(mi.Float, step_optical_depth)
        self.cells = FixedCells(self.step_size) if mode == "fixed" else \
            MajorantCells(self.step_size, self.step_optical_depth)

    def transmittance(self, tracker: Tracker, ray: mi.Ray3f, t_max: mi.Float,
                      sampler: mi.Sampler, active: mi.Bool) -> mi.Spectrum:
        """Marched transmittance ``exp(-sum sigma_t(mid) l)`` over ``[0, t_max]``: exact
        for the piecewise-constant medium; one random number (the jitter)."""
        return walk(tracker, ray, t_max, sampler, MarchedTransmittance(self), active)

    def __repr__(self):
        return (f"{self.mode} (step_size {self.step_size[0]:g}"
                + (f", step_optical_depth {self.step_optical_depth[0]:g})"
                   if self.mode == "majorant" else ")"))


# -- rules of the walk: whole cells -----------------------------------------------------
class MarchRule:
    """A rule that takes each cell of a march whole, with the coefficients at its
    midpoint; the walk stops once every channel's optical depth passes TAU_CUTOFF."""
    budget = None               # a march's work is bounded by its step (MAX_STEPS_PER_MARCH)

    def __init__(self, marcher: Marcher):
        self.segments = marcher.cells


class OpticalDepth:
    DRJIT_STRUCT = {"tau": mi.Spectrum}     # optical depth so far

    def __init__(self, tau=None):
        self.tau = tau


class MarchedTransmittance(MarchRule):
    """``tau += sigma_t(mid) l`` per cell; the result is ``exp(-tau)``."""
    label = "march_transmittance"

    def start(self, tracker, ray, t_in, t_out, sampler, active):
        return OpticalDepth(mi.Spectrum(0.0))

    def step(self, tracker, ray, sampler, cell, t, state, active):
        t1 = cell.t_end
        sigma_t = tracker.sigma_t(medium_interaction(ray, 0.5 * (t + t1)), active)
        state.tau = dr.select(active, state.tau + sigma_t * (t1 - t), state.tau)
        return dr.select(active, t1, t), state, active & (dr.min(state.tau) < TAU_CUTOFF)

    def finish(self, t, state, t_out, entered):
        return dr.exp(-state.tau)


class FlightState:
    DRJIT_STRUCT = {"tau_left": mi.Float,       # hero optical depth to the collision
                    "tau": mi.Spectrum,         # optical depth so far (chromatic only)
                    "sigma_t": mi.Spectrum,     # extinction at the collision
                    "sigma_s": mi.Spectrum,     # scattering at the collision
                    "Le": mi.Spectrum,          # emission at the collision
                    "scattered": mi.Bool}       # collided in the medium

    def __init__(self, tau_left=None, tau=None, sigma_t=None, sigma_s=None, Le=None,
                 scattered=None):
        self.tau_left, self.tau, self.sigma_t = tau_left, tau, sigma_t
        self.sigma_s, self.Le, self.scattered = sigma_s, Le, scattered


class MarchedFlight(MarchRule):
    r"""The next collision in the marched (piecewise-constant) medium.

    One exponential optical depth is drawn and spent cell by cell, so a cell of optical
    depth ``tau_i`` holds the collision with probability ``1 - exp(-tau_i)`` given the
    flight reached it, at the exact position within it: free-flight sampling of the
    piecewise-constant medium, with no null collisions. At a collision the throughput
    takes the albedo ``sigma_s / sigma_t`` (absorption as a weight rather than a coin
    flip: same expectation, less variance). Chromatic extinction: the hero channel's
    optical depth decides and
    :func:`~mitsuba_plugins.tracking.homogeneous.spectral_flight_weight` weights the path over
    channels, as in homogeneous media. With ``emission`` the medium's emission is
    collected at the collision (``beta sigma_a Le / sigma_t``, whose expectation is
    ``int T sigma_a Le dt``). The walk returns a :class:`FreeFlight`.
    """
    label = "march_flight"

    def __init__(self, marcher, beta, r_u, hero, chromatic: bool, emission: bool):
        super().__init__(marcher)
        self.beta, self.r_u, self.hero = beta, r_u, hero
        self.chromatic, self.emission = chromatic, emission

    def start(self, tracker, ray, t_in, t_out, sampler, active):
        entered = mi.Bool(active) & (t_in < t_out)
        return FlightState(-dr.log(1.0 - sampler.next_1d(entered)), mi.Spectrum(0.0),
                           mi.Spectrum(0.0), mi.Spectrum(0.0), mi.Spectrum(0.0), mi.Bool(False))

    def step(self, tracker, ray, sampler, cell, t0, state, active):
        t1 = cell.t_end
        props = tracker.properties(medium_interaction(ray, 0.5 * (t0 + t1)), active)
        sigma_t, sigma_s, Le = props.sigma_t, props.sigma_s, props.Le
        sigma_h = index_channel(sigma_t, self.hero) if self.chromatic else sigma_t[0]
        cell_tau = sigma_h * (t1 - t0)
        collide = active & (state.tau_left < cell_tau)
        d = dr.select(collide, state.tau_left / dr.select(collide, sigma_h, 1.0), t1 - t0)
        t = dr.select(collide, t0 + d, dr.select(active, t1, t0))
        if self.chromatic:
            state.tau = dr.select(active, state.tau + sigma_t * d, state.tau)
        state.tau_left = dr.select(active & ~collide, state.tau_left - cell_tau, state.tau_left)
        state.sigma_t = dr.select(collide, sigma_t, state.sigma_t)
        state.sigma_s = dr.select(collide, sigma_s, state.sigma_s)
        if self.emission:
            state.Le = dr.select(collide, Le, state.Le)
        state.scattered |= collide
        return t, state, active & ~collide

    def finish(self, t, state, t_out, entered):
        scattered, r_u = state.scattered, self.r_u
        if self.chromatic:
            weight, r_u_new = spectral_flight_weight(state.tau, state.sigma_t, scattered, r_u)
            r_u = dr.select(entered, r_u_new, r_u)
        else:
            weight = mi.Spectrum(dr.select(
                scattered, dr.rcp(dr.select(scattered, state.sigma_t[0], 1.0)), 1.0))
        beta_flight = dr.select(entered, self.beta * weight, self.beta)
        L_e = mi.Spectrum(0.0)
        if self.emission:
            L_e = dr.select(scattered, beta_flight * (state.sigma_t - state.sigma_s) * state.Le,
                            0.0)
        beta = dr.select(scattered, beta_flight * state.sigma_s, beta_flight)
        return FreeFlight(scattered, t, beta, r_u, L_e)


class SingleState:
    DRJIT_STRUCT = {"tau": mi.Spectrum,     # optical depth so far
                    "L": mi.Spectrum}       # light gathered (per unit beta)

    def __init__(self, tau=None, L=None):
        self.tau, self.L = tau, L


class MarchedSingle(MarchRule):
    r"""Single scattering along the ray in the marched medium.

    Per cell of length ``l`` with midpoint coefficients, the light scattered once
    towards the ray, :math:`\int_{cell} T(t)\, \sigma_s\, L_s(t)\, dt`, is estimated with
    one point from :func:`sample_cell_point` and ``in_scatter(medium, mei, active)``,
    an estimate of :math:`L_s` (one emitter sample with its phase function value,
    emitter pdf and shadow transmittance). The classic Riemann sum
    ``T sigma_s L_s dt`` is not used: with ``sigma_t dt > 1`` it scatters more light
    than enters the cell; the cell integral never does. With ``emission``, each cell
    adds ``T(t0) sigma_a Le`` times its cell integral.

    The walk returns a :class:`FreeFlight` that never scatters: ``beta`` times the
    marched transmittance, and ``L_e``, the radiance gathered (already times ``beta``).
    ``nee`` masks lanes allowed an emitter sample (depth).
    """
    label = "march_single"

    def __init__(self, marcher, beta, r_u, in_scatter, chromatic: bool, emission: bool,
                 nee: mi.Bool):
        super().__init__(marcher)
        self.beta, self.r_u, self.in_scatter, self.nee = beta, r_u, in_scatter, nee
        self.chromatic, self.emission = chromatic, emission

    def start(self, tracker, ray, t_in, t_out, sampler, active):
        return SingleState(mi.Spectrum(0.0), mi.Spectrum(0.0))

    def step(self, tracker, ray, sampler, cell, t0, state, active):
        t1 = cell.t_end
        length = t1 - t0
        props = tracker.properties(medium_interaction(ray, 0.5 * (t0 + t1)), active)
        sigma_t, sigma_s, Le = props.sigma_t, props.sigma_s, props.Le
        T0 = dr.exp(-state.tau)

        # one emitter sample from a point in the cell
        s, weight = sample_cell_point(sigma_t, length, sampler.next_1d(active), self.chromatic)
        lit = active & self.nee & dr.any(sigma_s > 0)
        medium = mi.MediumPtr(tracker.medium)
        mei = medium_interaction(ray, t0 + s)
        mei.medium = medium
        L = dr.select(lit, state.L + T0 * weight * sigma_s * self.in_scatter(medium, mei, lit),
                      state.L)
        if self.emission:
            L = dr.select(active, L + T0 * (sigma_t - sigma_s) * Le * cell_integral(sigma_t, length),
                          L)
        state.L = mi.Spectrum(L)     # spectral: the cell integral is a plain Array4f
        state.tau = dr.select(active, state.tau + sigma_t * length, state.tau)
        return dr.select(active, t1, t0), state, active & (dr.min(state.tau) < TAU_CUTOFF)

    def finish(self, t, state, t_out, entered):
        return FreeFlight(mi.Bool(False), mi.Float(t_out), self.beta * dr.exp(-state.tau),
                          self.r_u, self.beta * state.L)
