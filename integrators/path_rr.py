"""Path tracer with next-event estimation, MIS and configurable Russian roulette."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.mis import MIS
from mitsuba_plugins.params import SAMPLING_INTEGRATOR_BASE, Params, depth_limit
from mitsuba_plugins.surface import (EMITTER_SELECTIONS, RR_RULES, EmitterSelection,
                                     RussianRoulette, emission_mis, emitter_contribution,
                                     sample_emitter)
from mitsuba_plugins.validity import SampleGuard, refuse_gradients

VARIANT = mi.variant()


class PathRR(mi.SamplingIntegrator):
    r"""
    .. _integrator-path_rr:

    Path tracer with Russian roulette (:monosp:`path_rr`)
    -----------------------------------------------------

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path depth (-1 = unbounded; 1 = emitters seen directly; 2 = direct
         illumination). (Default: -1)
     * - rr_depth
       - |int|
       - Path depth (>= 1) at which Russian roulette starts. (Default: 5)
     * - rr_rule
       - |string|
       - ``throughput``: survival ``clamp(max(beta) * eta^2, rr_min_survival, 0.95)``
         (Mitsuba's rule when ``rr_min_survival = 0``); ``fixed``: survival
         ``rr_survival`` at every vertex. (Default: ``throughput``)
     * - rr_survival
       - |float|
       - Survival probability of the ``fixed`` rule, in (0, 1]. (Default: 0.95)
     * - rr_min_survival
       - |float|
       - Lower clamp of the ``throughput`` rule, in [0, 0.95]: bounds the weight 1/s a
         surviving path can gain (fewer fireflies). (Default: 0)
     * - emitter_selection
       - |string|
       - ``uniform`` (Mitsuba's) or ``power`` (proportional to emitted flux). (Default: ``uniform``)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: false)

    A drop-in for Mitsuba's ``path``: with default parameters it draws random numbers in
    the same order and renders the same image, bit for bit. Surfaces only: it ignores
    participating media (use ``volpath_delta``).

    Estimator (docs/method.md sections 4-5; Veach 1997, eq. 9.13 with the power heuristic):

    .. math::

        L \approx \sum_{k} \beta_k \Big( w_b\, L_e(x_k) + w_l\,
              \frac{f(x_k)\, L_e\, G}{p_l} \Big),\qquad
        \beta_{k+1} = \beta_k \frac{f \cos\theta}{p_b\, s_k},

    where :math:`s_k` is the Russian-roulette survival probability (1 before ``rr_depth``).
    """

    render_forward, render_backward = refuse_gradients("path_rr", "prb")

    ALLOWED = SAMPLING_INTEGRATOR_BASE + ("max_depth", "rr_depth", "rr_rule", "rr_survival",
                                          "rr_min_survival", "emitter_selection")

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.sample_guard = SampleGuard()  # counts and zeroes NaN/Inf samples
        p = Params(props, "path_rr", self.ALLOWED)
        self.max_depth = p.max_depth()
        self.rr = RussianRoulette(
            rr_depth=p.rr_depth(),
            rule=p.choice("rr_rule", "throughput", RR_RULES),
            survival=p.float("rr_survival", 0.95, lo=0.0, hi=1.0, lo_open=True),
            min_survival=p.float("rr_min_survival", 0.0, lo=0.0, hi=0.95))
        self.emitter_selection = p.choice("emitter_selection", "uniform", EMITTER_SELECTIONS)
        self.mis = MIS("power", 2.0)

    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: mi.Bool = True):
        if self.max_depth == 0:
            return mi.Spectrum(0.0), mi.Bool(False), []
        L, valid_ray = self.trace(scene, sampler, ray, active)
        return self.sample_guard(L, active), valid_ray, []

    @dr.syntax
    def trace(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f, active: mi.Bool):
        """The path loop: ``(L, valid_ray)``."""
        emitters = EmitterSelection(scene, self.emitter_selection)
        bsdf_ctx = mi.BSDFContext()
        max_depth = depth_limit(self.max_depth)

        # ------------------------------ loop state ------------------------------
        ray = mi.Ray3f(ray)                              # current ray
        L = mi.Spectrum(0.0)                             # radiance estimate
        beta = mi.Spectrum(1.0)                          # path throughput
        eta = mi.Float(1.0)                              # product of IOR ratios (for roulette)
        depth = mi.UInt32(0)                             # path vertices so far
        valid_ray = mi.Bool(not self.hide_emitters      # alpha: hit something or sees env
                            and scene.environment() is not None)
        prev_si = dr.zeros(mi.Interaction3f)             # previous vertex (MIS reference)
        prev_bsdf_pdf = mi.Float(1.0)                    # p_b of the direction that led here
        prev_bsdf_delta = mi.Bool(True)                  # ... drawn from a delta lobe (camera: yes)
        active = mi.Bool(active)                         # lanes still tracing
        pi = scene.ray_intersect_preliminary(ray, coherent=True, reorder=False, active=active)

        if dr.hint(self.hide_emitters, mode="scalar"):
            # Camera rays see through area emitters, as in Mitsuba's `path`.
            skip = pi.is_valid() & (pi.shape.emitter() != None) & active  # noqa: E711
            si_skip = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, skip)
            pi[skip] = self.skip_area_emitters(scene, si_skip.spawn_ray(ray.d), True, skip)

        while dr.hint(active, label="path_rr"):
            # ------------------------------ intersect ------------------------------
            si = pi.compute_surface_interaction(ray, mi.RayFlags.All)

            # ------------------------ emission with MIS ------------------------
            L = dr.fma(beta, emission_mis(scene, emitters, self.mis, si, prev_si,
                                          prev_bsdf_pdf, prev_bsdf_delta), L)
            active_next = (depth + 1 < max_depth) & si.is_valid()
            bsdf = si.bsdf(ray)

            # ------------------------ emitter sampling ------------------------
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds, em_weight, wo, active_em = sample_emitter(emitters, si, sampler.next_2d(), active_em)

            # --------------------------- BSDF sampling ---------------------------
            u1 = sampler.next_1d()
            u2 = sampler.next_2d()
            bsdf_val, p_b, bs, bsdf_weight = bsdf.eval_pdf_sample(bsdf_ctx, si, wo, u1, u2)
            L[active_em] = dr.fma(beta, emitter_contribution(self.mis, si, ds, em_weight, wo,
                                                             bsdf_val, p_b), L)

            # ------------------------- throughput update -------------------------
            bsdf_weight = si.to_world_mueller(bsdf_weight, -bs.wo, si.wi)
            ray = si.spawn_ray(si.to_world(bs.wo))
            beta *= bsdf_weight
            eta *= bs.eta
            valid_ray |= active & si.is_valid() & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
            prev_si = mi.Interaction3f(si)
            prev_bsdf_pdf = bs.pdf
            prev_bsdf_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)

            # ------------------------- Russian roulette -------------------------
            depth[si.is_valid()] += 1
            beta, alive = self.rr.apply(beta, eta, depth, sampler.next_1d())

            # ------------------------------ advance ------------------------------
            active = active_next & alive
            pi = scene.ray_intersect_preliminary(ray, coherent=False,
                                                 reorder=dr.flag(dr.JitFlag.LoopRecord),
                                                 active=active)

        return dr.select(valid_ray, L, 0.0), valid_ray

    def to_string(self):
        return (f"PathRR[\n  max_depth = {self.max_depth},\n  roulette = {self.rr},\n"
                f"  emitter_selection = {self.emitter_selection},\n"
                f"  hide_emitters = {self.hide_emitters}\n]")


mi.register_integrator("path_rr", lambda props: PathRR(props))
