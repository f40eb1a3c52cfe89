"""The path tracers' shared base and surface path loop.

:class:`PathIntegrator` parses the parameters every path tracer of ours shares, once
(as Mitsuba's ``ADIntegrator`` does), and owns ``sample``; a plugin adds its own
parameters in :meth:`PathIntegrator.configure` and its loop in :meth:`PathIntegrator.trace`.
The volumetric integrators extend it in :mod:`mitsuba_plugins.volume_loop`.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.guiding.sampling import Records, SurfaceRecords, mix_surface, still_guided
from mitsuba_plugins.loop_state import traced_once, widened
from mitsuba_plugins.mis import MIS
from mitsuba_plugins.params import Params, SAMPLING_INTEGRATOR_BASE, depth_limit
from mitsuba_plugins.path_vertex import (EmitterSelection, RussianRoulette, emission_mis,
                                         emitter_contribution, sample_emitter)
from mitsuba_plugins.validity import SampleGuard

VARIANT = mi.variant()

#: what a surface vertex records, as the ``f_wo`` of :meth:`Records.add` (which divides
#: the light gathered after the vertex by ``beta f_wo``): 1, so a record is ``f cos Li /
#: p``, the integrand of the reflected light, and a cell's histogram learns the product of
#: the incident light and the BSDF's cosine-weighted value (for the diffuse walls of one
#: cell, the cosine about their normal) instead of ``Li`` alone. Measured on the tuning
#: room (docs/benchmarks.md, twentieth session): a frozen field's relMSE over unguided
#: ``path_rr``'s 0.46 -> 0.41 (8^3 cells, fraction 0.2); online at 256 spp, 6 runs, twice
#: each alternating, 0.52 and 0.54 -> 0.48 and 0.47 per sample, 1.24x and 1.19x -> 1.39x
#: and 1.36x ``path``.
SURFACE_PRODUCT = 1.0

#: Largest allowed ``rr_max_survival``: below 1 so that a path in a medium of albedo 1
#: still ends (expected length after ``rr_depth`` at most 1 / (1 - 0.9999) vertices).
MAX_SURVIVAL = 0.9999


class PathIntegrator(mi.SamplingIntegrator):
    """Base of ``path_rr``, ``volpath_delta`` and ``volpath_raymarch``.

    Subclasses set ``NAME`` (the plugin name, used in messages), ``PARAMETERS`` (their
    own parameter names; ``max_depth``, ``rr_depth`` and Mitsuba's sampling-integrator
    parameters are always allowed) and ``render_forward`` / ``render_backward``
    (:func:`mitsuba_plugins.validity.refuse_gradients`).
    """
    NAME = "path"
    PARAMETERS: tuple = ()
    #: Default cap of the throughput roulette's survival (``rr_max_survival``): Mitsuba's.
    RR_MAX_SURVIVAL = 0.95

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.sample_guard = SampleGuard()  # counts and zeroes NaN/Inf samples
        p = Params(props, self.NAME,
                   SAMPLING_INTEGRATOR_BASE + ("max_depth", "rr_depth", "rr_max_survival")
                   + self.PARAMETERS)
        self.max_depth = p.max_depth()
        self.rr = RussianRoulette(rr_depth=p.rr_depth(), max_survival=p.float(
            "rr_max_survival", self.RR_MAX_SURVIVAL, lo=0.0, hi=MAX_SURVIVAL, lo_open=True))
        self.emitter_selection = "uniform"
        self.mis = MIS("power", 2.0)
        self.configure(p)

    def configure(self, p: Params) -> None:
        """Read the plugin's own parameters (``self.PARAMETERS``) from ``p``."""

    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: mi.Bool = True, guide=None):
        """Mitsuba's ``SamplingIntegrator.sample``; ``guide``: a pass of a guided render
        (:class:`~mitsuba_plugins.guided_render.GuidedPass`), handed to the loop."""
        if self.max_depth == 0:
            return mi.Spectrum(0.0), mi.Bool(False), []
        with traced_once():
            L, valid_ray = self.trace(scene, sampler, ray, medium, active, guide)
        return self.sample_guard(L, active), valid_ray, []

    def trace(self, scene, sampler, ray, medium, active, guide=None):
        """``(L, valid_ray)`` of one sample."""
        return trace_surfaces(self, scene, sampler, ray, active, guide)


@dr.syntax
def trace_surfaces(integrator, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f,
                   active: mi.Bool, guide=None):
    """The surface path loop of ``path_rr`` (and of the volumetric integrators in a
    scene without media): ``(L, valid_ray)``. ``integrator`` supplies the settings
    (``max_depth``, ``rr``, ``mis``, ``emitter_selection``, ``hide_emitters``).

    ``guide`` (:class:`~mitsuba_plugins.guided_render.GuidedPass`): at surfaces without
    delta or transmissive lobes, directions from the one-sample MIS mixture of the
    guiding field and the BSDF, and/or records that train the field
    (:func:`mitsuba_plugins.guiding.sampling.mix_surface`)."""
    emitters = EmitterSelection(scene, integrator.emitter_selection)
    bsdf_ctx = mi.BSDFContext()
    max_depth = depth_limit(integrator.max_depth)

    # ------------------------------ loop state ------------------------------
    ray = widened(mi.Ray3f(ray), ray)                # current ray (its time as wide)
    L = mi.Spectrum(0.0)                             # radiance estimate
    beta = mi.Spectrum(1.0)                          # path throughput
    eta = mi.Float(1.0)                              # product of IOR ratios (for roulette)
    depth = mi.UInt32(0)                             # path vertices so far
    valid_ray = mi.Bool(not integrator.hide_emitters  # alpha: hit something or sees env
                        and scene.environment() is not None)
    prev_si = dr.zeros(mi.Interaction3f)             # previous vertex (MIS reference)
    prev_pdf = mi.Float(1.0)                         # p_b of the direction that led here
    prev_delta = mi.Bool(True)                       # ... drawn from a delta lobe (camera: yes)
    active = mi.Bool(active)                         # lanes still tracing
    guided = guide is not None and guide.sampling    # directions from the field
    recording = guide is not None and guide.recording
    # the records of the training passes also find the field's portals
    portals = recording and getattr(guide.field, "portal_buffer", None) is not None
    records = (SurfaceRecords() if portals else Records()) if recording else None
    gain = mi.Float(1.0) if guided else None         # unguided throughput / beta (roulette)
    learnt_nee = guided and guide.nee                # emitter samples with learnt probability
    prev_q = mi.Float(1.0) if learnt_nee else 1.0    # ... at the previous vertex
    pi = scene.ray_intersect_preliminary(ray, coherent=True, reorder=False, active=active)

    if dr.hint(integrator.hide_emitters, mode="scalar"):
        # Camera rays see through area emitters, as in Mitsuba's `path`.
        skip = pi.is_valid() & (pi.shape.emitter() != None) & active  # noqa: E711
        si_skip = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, skip)
        pi[skip] = integrator.skip_area_emitters(scene, si_skip.spawn_ray(ray.d), True, skip)

    while dr.hint(active, label="path_rr"):
        # ------------------------------ intersect ------------------------------
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All)
        if dr.hint(portals, mode="scalar"):
            records.hit(dr.select(si.is_valid(), si.t, dr.inf), active)

        # ------------------------ emission with MIS ------------------------
        L = dr.fma(beta, emission_mis(scene, emitters, integrator.mis, si, prev_si,
                                      prev_pdf, prev_delta, prev_q), L)
        active_next = (depth + 1 < max_depth) & si.is_valid()
        bsdf = si.bsdf(ray)

        # ------------------------ emitter sampling ------------------------
        active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        eligible, q = active_em, 1.0
        record_nee = recording and guide.lane_weight is not None
        if dr.hint(learnt_nee or record_nee, mode="scalar"):
            # the cell's side this vertex faces (GuidingField.nee_index)
            side_n = dr.select(si.wi.z < 0, -si.sh_frame.n, si.sh_frame.n)
            nee_at = guide.field.nee_index(guide.field.cell(si.p), side_n)
        if dr.hint(learnt_nee, mode="scalar"):
            # with the learnt probability q, weighted 1 / q and in the MIS weights as a
            # density q p_l (GuidingField.nee_probabilities)
            q = dr.select(eligible, guide.field.nee_probability(nee_at, eligible), 1.0)
            active_em = eligible & (sampler.next_1d() < q)
        ds, em_weight, wo, active_em = sample_emitter(emitters, si, sampler.next_2d(), active_em)

        # --------------------------- BSDF sampling ---------------------------
        u1 = sampler.next_1d()
        u2 = sampler.next_2d()
        bsdf_val, p_b, bs, bsdf_weight = bsdf.eval_pdf_sample(bsdf_ctx, si, wo, u1, u2)
        if dr.hint(guided or recording, mode="scalar"):
            flags = bsdf.flags()
            guidable = active_next & ~mi.has_flag(flags, mi.BSDFFlags.Delta) & \
                ~mi.has_flag(flags, mi.BSDFFlags.Transmission)
        if dr.hint(guided, mode="scalar"):
            p_b, bs, bsdf_weight, g, mis_pdf = mix_surface(
                guide.field, guide.fraction, bsdf, bsdf_ctx, si, ds.d, p_b, bs, bsdf_weight,
                sampler.next_1d(), u2, guidable & still_guided(gain), active_em,
                guide.portal)
        L_pre = L
        nee = emitter_contribution(integrator.mis, si, ds,
                                   em_weight / q if learnt_nee else em_weight, wo, bsdf_val,
                                   p_b, frac_l=q)
        L = dr.select(active_em, dr.fma(beta, nee, L), L)
        if dr.hint(record_nee, mode="scalar"):
            guide.field.record_nee(nee_at, dr.select(active_em, dr.mean(beta * nee), 0.0),
                                   q, eligible, guide.lane_weight)
        if dr.hint(recording, mode="scalar"):
            # a surface record is the light the sampled direction brought over the
            # throughput before it, f cos Li / p (SURFACE_PRODUCT)
            records = records.add(guide.field, si.p, si.to_world(bs.wo), L, beta,
                                  SURFACE_PRODUCT, sampler.next_1d(), guidable, L_pre)

        # ------------------------- throughput update -------------------------
        bsdf_weight = si.to_world_mueller(bsdf_weight, -bs.wo, si.wi)
        ray = si.spawn_ray(si.to_world(bs.wo))
        beta *= bsdf_weight
        eta *= bs.eta
        valid_ray |= active & si.is_valid() & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
        prev_si = mi.Interaction3f(si)
        # (a guided sample's MIS density: mix_surface)
        prev_pdf = mis_pdf if guided else bs.pdf
        prev_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        if dr.hint(learnt_nee, mode="scalar"):
            prev_q = q

        # ------------------------- Russian roulette -------------------------
        depth[si.is_valid()] += 1
        if dr.hint(guided, mode="scalar"):
            gain *= g
        beta, alive = integrator.rr.apply(beta, eta, depth, sampler.next_1d(),
                                          gain=gain if guided else None)

        # ------------------------------ advance ------------------------------
        active = active_next & alive
        pi = scene.ray_intersect_preliminary(ray, coherent=False,
                                             reorder=dr.flag(dr.JitFlag.LoopRecord),
                                             active=active)

    if dr.hint(recording, mode="scalar"):
        records.flush(guide.field, L, mi.Bool(True),
                      1.0 if guide.lane_weight is None else guide.lane_weight)
    return dr.select(valid_ray, L, 0.0), valid_ray
