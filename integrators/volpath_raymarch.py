"""Biased ray-marching volumetric path tracer: single or multiple scattering on the
piecewise-constant medium a march sees (docs/method.md section 10)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.params import PluginParameterError
from mitsuba_plugins.tracking.homogeneous import FreeFlight, homogeneous_transmittance
from mitsuba_plugins.tracking.marching import (MarchedFlight, MarchedSingle, Marcher,
                                               STEP_MODES, sample_cell_point)
from mitsuba_plugins.tracking.scene_media import SceneMedia
from mitsuba_plugins.tracking.shadow_rays import shadow_transmittance
from mitsuba_plugins.tracking.trackers import medium_interaction
from mitsuba_plugins.tracking.walk import walk
from mitsuba_plugins.validity import refuse_gradients
from mitsuba_plugins.volume_loop import VolumeStrategy, VolumetricIntegrator

VARIANT = mi.variant()

MODES = ("single", "multi")
#: Default step in world units: 100 steps across the 2-unit media of scenes/.
DEFAULT_STEP_SIZE = 0.02
#: Most steps one march may take across a medium: a step that would need more is
#: refused at render time (a step of 1e-9 took over 150 s for 64 rays).
MAX_STEPS_PER_MARCH = 1e5
#: Default largest optical depth of a cell in ``majorant`` step mode.
DEFAULT_STEP_OPTICAL_DEPTH = 0.25


class VolpathRaymarch(VolumetricIntegrator):
    r"""
    .. _integrator-volpath_raymarch:

    Ray-marching volumetric path tracer (:monosp:`volpath_raymarch`)
    ----------------------------------------------------------------

    .. pluginparameters::

     * - mode
       - |string|
       - ``single``: light scattered at most once in media (surfaces as in
         ``path_rr``); ``multi``: multiple scattering. (Default: ``multi``)
     * - step_size
       - |float|
       - March step in world units, > 0 (the largest step in ``majorant`` mode).
         (Default: 0.02)
     * - step_mode
       - |string|
       - ``fixed``: steps of ``step_size``; ``majorant``: in each cell of the majorant
         grid, steps of ``min(step_size, step_optical_depth / sigma_maj)``, and empty
         cells crossed in one step. (Default: ``fixed``)
     * - step_optical_depth
       - |float|
       - Largest optical depth of a step in ``majorant`` mode, > 0. (Default: 0.25)
     * - max_depth
       - |int|
       - Longest path depth (-1 = unbounded), counted as in Mitsuba's ``volpath``:
         medium scattering and non-null surface events. (Default: -1)
     * - rr_depth
       - |int|
       - Depth (>= 1) at which Russian roulette starts. (Default: 5)
     * - rr_max_survival
       - |float|
       - Cap of the roulette's survival probability, in (0, 0.9999]. (Default: 0.95,
         Mitsuba's; 0.99-0.999 for albedo near 1, see benchmarks/results/dense_raymarch.md)
     * - hide_emitters
       - |bool|
       - Hide emitters seen directly (also through media). (Default: false)

    A biased, consistent estimator: heterogeneous media are marched, i.e. replaced
    along each ray by the piecewise-constant medium whose value in each cell is the
    extinction (and albedo, emission) at the cell's midpoint; the cell grid is
    jittered per ray. Light transport in that medium is then computed *exactly*
    (:mod:`mitsuba_plugins.tracking.marching`), so the bias is the midpoint-quadrature error
    of the optical depth alone, and it vanishes as the step shrinks
    (``benchmarks/results/volpath_raymarch.md`` measures it per step size). Homogeneous
    media are never marched: their transmittance is analytic, as in ``volpath_delta``.

    * ``single``: along every ray segment in a medium, each cell of length :math:`l`
      adds :math:`T(t_0)\, \sigma_s \int_0^l e^{-\sigma_t s} L_s(s)\, ds`, estimated
      with one point drawn in the cell and one emitter sample there (phase function,
      emitter pdf and marched shadow transmittance included); the segment multiplies
      the throughput by its marched transmittance. Paths continue only at surfaces
      (NEE + BSDF sampling + MIS, as ``path_rr``). With ``max_depth = 2`` this
      estimates what Mitsuba's ``volpath`` does with ``max_depth = 2``.
    * ``multi``: free flights are drawn in the marched medium (one exponential optical
      depth spent cell by cell, so a cell holds the collision with probability
      :math:`1 - e^{-\sigma_t(p_{mid})\, l}`); at a collision the throughput takes the
      albedo and the path scatters (phase sampling), with an emitter sample at every
      scattering vertex whose shadow transmittance is marched. The path loop, MIS and
      Russian roulette are ``volpath_delta``'s.

    Emissive ``grid_medium`` emission is included in both modes. The step size is an
    opaque Dr.Jit value: changing it between renders reuses the compiled kernel.
    """

    render_forward, render_backward = refuse_gradients("volpath_raymarch", "prbvolpath")

    NAME = "volpath_raymarch"
    PARAMETERS = ("mode", "step_size", "step_mode", "step_optical_depth")

    def configure(self, p):
        self.mode = p.choice("mode", "multi", MODES)
        self.step_size = p.float("step_size", DEFAULT_STEP_SIZE, lo=0.0, lo_open=True)
        self.step_mode = p.choice("step_mode", "fixed", STEP_MODES)
        self.step_optical_depth = p.float("step_optical_depth", DEFAULT_STEP_OPTICAL_DEPTH,
                                          lo=0.0, lo_open=True)
        self.strategy = RayMarchingStrategy(self)

    def to_string(self):
        return (f"VolpathRaymarch[\n  mode = {self.mode},\n  step_mode = {self.step_mode},\n"
                f"  step_size = {self.step_size:g},\n"
                f"  step_optical_depth = {self.step_optical_depth:g},\n"
                f"  max_depth = {self.max_depth},\n  roulette = {self.rr},\n"
                f"  hide_emitters = {self.hide_emitters}\n]")


class RayMarchingStrategy(VolumeStrategy):
    """The medium phase of ``volpath_raymarch``: marched flights, single scattering or
    marched shadow rays in heterogeneous media; homogeneous media are never marched
    (``multi``: the base's analytic flight)."""

    def __init__(self, settings: VolpathRaymarch):
        self.mode, self.step_size = settings.mode, settings.step_size
        self.step_mode, self.step_optical_depth = settings.step_mode, settings.step_optical_depth

    def shadow_estimator(self, media: SceneMedia) -> Marcher:
        # Built at each render from the plugin's parameters; the steps are opaque.
        extent = media.extent()
        if media.heterogeneous and extent / self.step_size > MAX_STEPS_PER_MARCH:
            raise PluginParameterError(
                f"volpath_raymarch: parameter 'step_size' = {self.step_size:g} would cut a "
                f"march across this scene's media (extent {extent:.3g}) into up to "
                f"{extent / self.step_size:.3g} steps; allowed: >= "
                f"{extent / MAX_STEPS_PER_MARCH:.3g} here (at most {MAX_STEPS_PER_MARCH:g} "
                "steps per march)")
        if self.step_mode == "majorant" and media.heterogeneous:
            # steps of step_optical_depth / sigma_maj: the majorant's optical depth along a
            # line of cells sets the count
            depth = max(t.march_grid.line_optical_depth() for t in media.trackers.values())
            steps = depth / self.step_optical_depth
            if steps > MAX_STEPS_PER_MARCH:
                raise PluginParameterError(
                    f"volpath_raymarch: parameter 'step_optical_depth' = "
                    f"{self.step_optical_depth:g} would cut a march across this scene's media "
                    f"(majorant optical depth up to about {depth:.3g}) into about "
                    f"{steps:.3g} steps; allowed: >= {depth / MAX_STEPS_PER_MARCH:.3g} here "
                    f"(at most {MAX_STEPS_PER_MARCH:g} steps per march)")
        return Marcher(self.step_mode, self.step_size, self.step_optical_depth)

    def gathers_light(self, media: SceneMedia) -> bool:
        return self.mode == "single" or media.emission

    def reach(self, ctx, medium, ray, active):
        # single scattering draws its own point along the whole segment
        return super().reach(ctx, medium, ray, active) if self.mode == "multi" else None

    def homogeneous_flight(self, ctx, medium, ray, t_max, beta, r_u, nee, active):
        if self.mode == "multi":
            return super().homogeneous_flight(ctx, medium, ray, t_max, beta, r_u, nee, active)
        # Single scattering: the whole segment is one cell of known transmittance.
        sigma_s, _, sigma_t = medium.get_scattering_coefficients(medium_interaction(ray, 0.0),
                                                                 active)
        sigma_t = mi.Spectrum(sigma_t)
        s, weight = sample_cell_point(sigma_t, t_max, ctx.sampler.next_1d(active),
                                      ctx.media.chromatic_homogeneous)
        mei = medium_interaction(ray, s)
        mei.medium = medium
        lit = active & nee
        L_e = dr.select(lit, beta * weight * mi.Spectrum(sigma_s) *
                        in_scatter(ctx, medium, mei, lit), 0.0)
        return FreeFlight(mi.Bool(False), mi.Float(0.0),
                          beta * homogeneous_transmittance(sigma_t, t_max), r_u, L_e)

    def heterogeneous_flight(self, ctx, tracker, ray, t_max, beta, r_u, nee, active):
        media = ctx.media
        if self.mode == "multi":
            rule = MarchedFlight(ctx.estimator, beta, r_u, ctx.hero, media.chromatic_heterogeneous,
                                 media.emission)
        else:
            def gather(medium, mei, active):
                return in_scatter(ctx, medium, mei, active)
            rule = MarchedSingle(ctx.estimator, beta, r_u, gather, media.chromatic_heterogeneous,
                                 media.emission, nee)
        return walk(tracker, ray, t_max, ctx.sampler, rule, active)


def in_scatter(ctx, medium: mi.MediumPtr, mei: mi.MediumInteraction3f,
               active: mi.Bool) -> mi.Spectrum:
    """Light arriving at ``mei`` and scattered towards ``-ray``, per unit ``sigma_s``:
    one emitter sample, ``p(w_l, -w) Le T / p_l`` (the phase function and the emitter
    pdf that the classic single-scattering pseudocode drops)."""
    ds, em_weight = ctx.emitters.sample_direction(mei, ctx.sampler.next_2d(active), active,
                                                  test_visibility=False)
    active = active & (ds.pdf != 0)
    T = shadow_transmittance(ctx.scene, ctx.media, mei, ds, medium, ctx.sampler,
                             ctx.estimator, active)
    phase_val, _ = medium.phase_function().eval_pdf(ctx.phase_ctx, mei, ds.d, active)
    return dr.select(active, em_weight * T * mi.Spectrum(phase_val), 0.0)


mi.register_integrator("volpath_raymarch", lambda props: VolpathRaymarch(props))
