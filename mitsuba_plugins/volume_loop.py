"""The volumetric path loop and its medium phase (docs/method.md sections 6-10).

:func:`trace_volumes` is the one path loop of ``volpath_delta`` and ``volpath_raymarch``.
What happens while a ray crosses a medium is a *strategy* object handed to it
(:class:`VolumeStrategy`): delta tracking (unbiased) or ray marching (biased) are two
strategies, not two subclasses of one loop. :class:`VolumetricIntegrator` parses the
shared parameters (via :class:`~mitsuba_plugins.path_loop.PathIntegrator`) and runs the
surface loop in scenes without media.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.guiding import distance
from mitsuba_plugins.guiding.sampling import Records, resample, roulette, still_guided
from mitsuba_plugins.instrument import count, settings
from mitsuba_plugins.loop_state import widened
from mitsuba_plugins.params import depth_limit
from mitsuba_plugins.path_loop import PathIntegrator
from mitsuba_plugins.path_vertex import EmitterSelection, emission_mis, emitter_contribution
from mitsuba_plugins.tracking import empty_scatter, equiangular
from mitsuba_plugins.tracking.homogeneous import (FreeFlight, homogeneous_free_flight,
                                                  sample_exponential)
from mitsuba_plugins.tracking.replay import SUB_PATH_EVENT, replay_homogeneous, replay_vertex
from mitsuba_plugins.tracking.scene_media import SceneMedia
from mitsuba_plugins.tracking.shadow_rays import shadow_transmittance
from mitsuba_plugins.tracking.trackers import Tracker, index_channel, medium_interaction

VARIANT = mi.variant()


class VolumeContext:
    """What the medium phase of a path needs besides its loop state, for one render:
    the scene, its media, emitter selection, sampler, phase-function context, hero
    channel and shadow-ray transmittance estimator. A plain holder, never loop state.
    In a gradient replay also the :class:`~mitsuba_plugins.tracking.replay.Replay` and, set at
    each vertex, ``remaining``: the radiance the path gathers from there on."""

    def __init__(self, scene, media, emitters, sampler, phase_ctx, hero, estimator,
                 replay=None):
        self.scene, self.media, self.emitters, self.sampler = scene, media, emitters, sampler
        self.phase_ctx, self.hero, self.estimator = phase_ctx, hero, estimator
        self.replay, self.remaining = replay, None
        self.drawn = None

    def at_vertex(self, remaining: mi.Spectrum) -> None:
        """Set ``remaining`` (a call, not an assignment: the path loop must not take
        this holder for loop state)."""
        self.remaining = remaining

    def at_flight(self, u: mi.Float, sigma_s: mi.Spectrum, sigma_t: mi.Spectrum) -> None:
        """Set ``drawn``: the number the next analytic flight draws its distance from
        and the medium's coefficients, read before the ray was intersected
        (:meth:`VolumeStrategy.reach`)."""
        self.drawn = (u, sigma_s, sigma_t)


class VolumeStrategy:
    """The medium phase of :func:`trace_volumes`: what a flight through a medium does.
    Both flights take the same arguments and return a :class:`FreeFlight` for the
    ``active`` lanes: ``(ctx, medium_or_tracker, ray, t_max, beta, r_u, nee, active)``,
    ``nee`` masking lanes whose depth allows an emitter sample in a medium. By default a
    homogeneous medium's flight is analytic (:func:`analytic_flight`); a strategy says
    how to cross a heterogeneous one and how shadow rays are estimated."""

    def shadow_estimator(self, media: SceneMedia):
        """Shadow-ray transmittance estimator (an object with ``transmittance``)."""
        raise NotImplementedError

    def gathers_light(self, media: SceneMedia) -> bool:
        """Whether flights gather light (``FreeFlight.L_e``) in this scene."""
        return media.emission

    def reach(self, ctx: VolumeContext, medium: mi.MediumPtr, ray: mi.Ray3f,
              active: mi.Bool):
        """How far the path ray needs to be intersected: on lanes in a homogeneous
        medium, the distance its analytic flight will collide at (drawn here, before
        the intersection, from the number the flight then uses: the same estimator
        and random numbers); ``inf`` elsewhere. In a dense medium most flights end
        before the next surface: the intersection is then searched only up to the
        collision and no surface interaction is computed, as in Mitsuba's ``volpath``
        (issue 29). None: this strategy's homogeneous flights draw their own."""
        if not ctx.media.homogeneous:
            return None
        mine = active & (medium != None) & medium.is_homogeneous()  # noqa: E711
        u = ctx.sampler.next_1d(mine)
        sigma_s, _, sigma_t = medium.get_scattering_coefficients(medium_interaction(ray, 0.0),
                                                                 mine)
        sigma_t = mi.Spectrum(sigma_t)
        ctx.at_flight(u, mi.Spectrum(sigma_s), sigma_t)
        rate = index_channel(sigma_t, ctx.hero) if ctx.media.chromatic_homogeneous \
            else sigma_t[0]
        return dr.select(mine, sample_exponential(u, rate), dr.inf)

    def homogeneous_flight(self, ctx: VolumeContext, medium: mi.MediumPtr, ray: mi.Ray3f,
                           t_max: mi.Float, beta: mi.Spectrum, r_u: mi.Spectrum,
                           nee: mi.Bool, active: mi.Bool) -> FreeFlight:
        return analytic_flight(ctx, medium, ray, t_max, beta, r_u, active)

    def heterogeneous_flight(self, ctx: VolumeContext, tracker: Tracker, ray: mi.Ray3f,
                             t_max: mi.Float, beta: mi.Spectrum, r_u: mi.Spectrum,
                             nee: mi.Bool, active: mi.Bool) -> FreeFlight:
        raise NotImplementedError


def analytic_flight(ctx: VolumeContext, medium: mi.MediumPtr, ray: mi.Ray3f, t_max: mi.Float,
                    beta: mi.Spectrum, r_u: mi.Spectrum, active: mi.Bool) -> FreeFlight:
    """Analytic free flight in homogeneous media (docs/method.md section 7)."""
    if ctx.drawn is None:
        sigma_s, _, sigma_t = medium.get_scattering_coefficients(
            medium_interaction(ray, 0.0), active)
        u = ctx.sampler.next_1d(active)
    else:
        u, sigma_s, sigma_t = ctx.drawn
    chromatic = ctx.media.chromatic_homogeneous
    t, scattered, weight, r_u_new = homogeneous_free_flight(
        mi.Spectrum(sigma_t), t_max, u, chromatic, ctx.hero, r_u)
    grad = None
    if ctx.replay is not None:
        grad = replay_homogeneous(ctx.replay, medium, ray, dr.select(scattered, t, t_max),
                                  ctx.remaining, active, active & scattered)
    return FreeFlight(active & scattered, t,
                      beta * dr.select(scattered, mi.Spectrum(sigma_s) * weight, weight),
                      r_u_new if chromatic else r_u, mi.Spectrum(0.0), grad)


def free_flight(ctx: VolumeContext, strategy: VolumeStrategy, medium: mi.MediumPtr,
                ray: mi.Ray3f, t_max: mi.Float, beta: mi.Spectrum, r_u: mi.Spectrum,
                nee: mi.Bool, active: mi.Bool) -> FreeFlight:
    """The flight of ``ray`` through its medium up to the surface at ``t_max``: where
    it collides (if it does), the throughput and spectral-MIS ratios after it and
    the medium light gathered (times ``beta``). Lanes outside media keep their values."""
    outside = FreeFlight(mi.Bool(False), mi.Float(0.0), mi.Spectrum(beta), mi.Spectrum(r_u),
                         mi.Spectrum(0.0))

    def homogeneous(mask):
        return strategy.homogeneous_flight(ctx, medium, ray, t_max, beta, r_u, nee, mask)

    def heterogeneous(tracker, mask):
        return strategy.heterogeneous_flight(ctx, tracker, ray, t_max, beta, r_u, nee, mask)
    return ctx.media.dispatch(medium, active, outside, homogeneous, heterogeneous)


class VolumetricIntegrator(PathIntegrator):
    """Base of the volumetric integrators: ``self.strategy`` (set in ``configure``)
    is the medium phase; a scene without media runs the surface loop."""
    strategy: VolumeStrategy
    #: Threshold of the Russian roulette between a shadow ray's pieces (0: none; see
    #: :meth:`mitsuba_plugins.tracking.shadow_rays.TransmittancePass.roulette`).
    shadow_roulette = 0.0

    def trace(self, scene, sampler, ray, medium, active, guide=None):
        # derived per render (a guided render's passes share it): what the kernel needs
        media = guide.media if guide is not None and guide.media is not None else \
            SceneMedia(scene)
        if not media.any:
            return super().trace(scene, sampler, ray, medium, active)   # nothing to guide
        medium = dr.zeros(mi.MediumPtr) if medium is None else mi.MediumPtr(medium)
        return trace_volumes(self, self.strategy, scene, sampler, ray, medium, media, active,
                             guide=guide)


@dr.syntax
def trace_volumes(integrator, strategy, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f,
                  medium: mi.MediumPtr, media: SceneMedia, active: mi.Bool, replay=None,
                  guide=None, shadows=None):
    """The path loop with media: ``(L, valid_ray)``. One iteration per vertex, a
    real collision in a medium or a surface (null surfaces included). ``integrator``
    supplies the settings (as in :func:`~mitsuba_plugins.path_loop.trace_surfaces`),
    ``strategy`` the medium phase (:class:`VolumeStrategy`).

    ``replay`` (:class:`~mitsuba_plugins.tracking.replay.Replay`): the same path again,
    propagating derivatives (:mod:`mitsuba_plugins.tracking.replay`); returns ``(L, valid_ray,
    tangent)``, the tangent being 0 in backward mode.

    ``guide`` (:class:`~mitsuba_plugins.guided_render.GuidedPass`): scattering directions
    in media resampled in proportion to the guiding field, and/or records that train it
    (:mod:`mitsuba_plugins.guiding`).

    In a replay through a gray heterogeneous medium a path that ends goes on as the
    sub-path of one point where ``sigma_t = 0`` (:mod:`mitsuba_plugins.tracking.empty_scatter`):
    its first vertex a real collision there, its light that term's ``L_s``.

    ``shadows`` (:class:`~mitsuba_plugins.tracking.replay.ShadowStore`, both passes of a
    gradient render): shadow rays draw from streams of their own; the primal pass keeps
    their estimates and the replay reads them instead of walking again."""
    emitters = EmitterSelection(scene, integrator.emitter_selection)
    bsdf_ctx = mi.BSDFContext()
    phase_ctx = mi.PhaseFunctionContext(sampler)
    max_depth = depth_limit(integrator.max_depth)
    hero = mi.UInt32(0)                              # channel that decides (spectral MIS)
    if dr.hint(media.chromatic, mode="scalar"):
        n = dr.size_v(mi.Spectrum)
        hero = mi.UInt32(dr.minimum(sampler.next_1d(active) * n, n - 1))
    ctx = VolumeContext(scene, media, emitters, sampler, phase_ctx, hero,
                        strategy.shadow_estimator(media), replay)
    eq = replay is None and equiangular.traced(integrator, scene, media)
    gd = replay is None and not eq and distance.traced(guide, media) \
        and "nee" in settings.terms
    learn_light = distance.learning(guide)
    # emitter samples at guided points take lamps' whole contribution (LightGrid.on_lamp)
    lamp_nee = gd and bool(guide.light.lamp_boxes)

    # ------------------------------ loop state ------------------------------
    ray = mi.Ray3f(ray)                              # current ray (unit direction)
    medium = mi.MediumPtr(medium)                    # medium the ray travels in
    L = mi.Spectrum(0.0)                             # radiance estimate
    beta = mi.Spectrum(1.0)                          # throughput, already / mean(r_u)
    r_u = widened(mi.Spectrum(1.0), ray)             # spectral-MIS pdf ratios (mean 1)
    eta = mi.Float(1.0)                              # product of IOR ratios (for roulette)
    depth = mi.UInt32(0)                             # real vertices so far
    valid_ray = mi.Bool(not integrator.hide_emitters  # alpha: hit something or sees env
                        and scene.environment() is not None)
    prev_si = dr.zeros(mi.Interaction3f)             # last real vertex (MIS reference)
    prev_pdf = mi.Float(1.0)                         # p_b / phase pdf of the direction
    prev_delta = mi.Bool(True)                       # ... not reachable by NEE (camera: yes)
    prev_point = mi.Bool(False) if lamp_nee else None  # ... its emitter sample at a guided point
    active = mi.Bool(active)                         # lanes still tracing
    grad = widened(mi.Spectrum(0.0), ray)            # tangent (forward-mode replay)
    guided = guide is not None and guide.sampling    # directions from the field
    recording = guide is not None and guide.recording
    records = Records() if recording else None       # the field's training records
    steered = guided and guide.roulette > 0           # roulette by the learnt radiance
    rr_ref = mi.Float(0.0) if steered else None      # ... the path's score at its first vertex
    gain = mi.Float(1.0) if guided else None         # unguided throughput / beta (roulette)
    empty = empty_scatter.for_replay(replay, media)
    forced = widened(mi.Bool(False), ray)            # a sub-path's first vertex: at ray.o
    dL_path = None if replay is None else replay.dL  # the adjoint (silenced in sub-paths)
    event = None if shadows is None else widened(mi.UInt32(0), ray)  # iterations (store)

    while dr.hint(active, label="volpath_delta"):
        # ------------------------------ intersect ------------------------------
        # equiangular sampling needs the segment's end: no flight drawn before; guided
        # points need it too, and take the coefficients read with the flight's number
        reach = None if eq else strategy.reach(ctx, medium, ray, active)
        # the lanes whose medium the light grid shapes (LightGrid.takes), from the
        # extinction the flight's number was drawn with
        shaped = guide.light.takes(mi.Bool(True), ctx.drawn[2]) if gd else None
        if dr.hint(reach is None, mode="scalar"):
            si = scene.ray_intersect(ray, mi.RayFlags.All, False, active)
        elif dr.hint(gd, mode="scalar"):
            # the segment's end on every lane whose medium the light grid shapes (its
            # guided point is drawn over all of it), the surface interaction only where
            # the flight will reach it; in a dense homogeneous medium (LightGrid.takes)
            # the intersection only up to the flight's collision, as unguided: the dense
            # family's cube pairs (a near-empty box beside a dense one) searched whole
            # segments at every one of their ~12 vertices per camera ray
            far = dr.select(shaped, ray.maxt, dr.minimum(ray.maxt, reach))
            pi = scene.ray_intersect_preliminary(
                mi.Ray3f(ray.o, ray.d, far, ray.time, ray.wavelengths), False, active)
            si = pi.compute_surface_interaction(ray, mi.RayFlags.All, active & (pi.t <= reach))
            t_end = dr.select(active, pi.t, dr.inf)
            end_bsdf = pi.shape.bsdf()
        else:
            si = scene.ray_intersect(mi.Ray3f(ray.o, ray.d, dr.minimum(ray.maxt, reach),
                                              ray.time, ray.wavelengths),
                                     mi.RayFlags.All, False, active)
        count("intersections", active)
        if dr.hint(not gd, mode="scalar"):
            t_end = si.t                      # where the segment ends

        # ------------------- free flight through the medium -------------------
        if dr.hint(replay is not None, mode="scalar"):
            ctx.at_vertex(replay.L_primal - L)
            replay.at_depth(depth)
        if dr.hint(empty is not None, mode="scalar"):
            empty.silence(replay, dL_path)
        flight = free_flight(ctx, strategy, medium, ray, t_end, beta, r_u,
                             depth + 1 < max_depth, active if empty is None else active & ~forced)
        if dr.hint(eq, mode="scalar"):
            # a second light sample along the segment (where a flight's vertex would
            # sample one), by equiangular sampling toward a point or spot light
            eq_lanes = active & (medium != None) & medium.is_homogeneous() \
                & medium.use_emitter_sampling() & (depth + 1 < max_depth)  # noqa: E711
            L_eq, eq_sigma_t = equiangular.gather(ctx, ray, medium, si.t, beta,
                                                  integrator.shadow_roulette, eq_lanes)
            L += L_eq
            valid_ray |= dr.any(L_eq != 0)
        bsdf = si.bsdf(ray)                 # the surface the segment ends at, if any
        # whether the segment ends at a surface that samples emitters (with guided
        # points known on every lane, not only where the flight reaches it)
        smooth = (t_end < dr.inf) & mi.has_flag((end_bsdf if gd else bsdf).flags(),
                                                mi.BSDFFlags.Smooth)
        if dr.hint(gd, mode="scalar"):
            # the segment's emitter sample at a point drawn toward where the learnt
            # once-scattered light is (guiding.distance), not at its free-flight vertex
            gd_lanes = active & (medium != None) & medium.is_homogeneous() \
                & medium.use_emitter_sampling() & (depth + 1 < max_depth)  # noqa: E711
            gd_lanes &= shaped
            gd_point = distance.plan(guide.light, ray, ctx.drawn[1:], t_end, smooth,
                                     gd_lanes, sampler.next_1d(gd_lanes))
            gd_beta = beta * gd_point.factor
        if dr.hint(empty is not None, mode="scalar"):
            empty = empty.consider(replay, media, medium, ray,
                                   dr.select(flight.scattered, flight.t, si.t), beta, depth,
                                   depth + 1 < max_depth, replay.L_primal - L, active)
        beta = flight.beta
        r_u = flight.r_u
        scattered = flight.scattered
        t_s = flight.t
        if dr.hint(empty is not None, mode="scalar"):
            scattered |= forced
            t_s = dr.select(forced, 0.0, t_s)
            forced = mi.Bool(False)
        if dr.hint(replay is not None, mode="scalar"):
            grad += flight.grad
        if dr.hint(strategy.gathers_light(media), mode="scalar"):
            L += flight.L_e
            valid_ray |= dr.any(flight.L_e != 0)

        mei = medium_interaction(ray, t_s)
        mei.medium = medium

        # ------------------------ emission with MIS ------------------------
        surface = active & ~scattered
        shown = surface if not integrator.hide_emitters else surface & (depth > 0)
        if dr.hint("emission" not in settings.terms, mode="scalar"):
            shown = mi.Bool(False)
        Le = emission_mis(scene, emitters, integrator.mis, si, prev_si, prev_pdf, prev_delta)
        if dr.hint(lamp_nee, mode="scalar"):   # a lamp's light there: the point's sample
            # (an escaped ray's si.p is no point of a light: never counted a lamp's)
            Le = dr.select(prev_point & si.is_valid() & guide.light.on_lamp(si.p), 0.0, Le)
        L[shown] = dr.fma(beta, Le, L)

        # --------------------- the vertex: scatter or surface ---------------------
        on_surface = surface & si.is_valid()
        phase = medium.phase_function()
        ref = mi.Interaction3f(dr.select(scattered, t_s, si.t), ray.time, ray.wavelengths,
                               dr.select(scattered, mei.p, si.p),
                               dr.select(scattered, mi.Normal3f(0.0), si.n))
        active_next = (depth + 1 < max_depth) & (scattered | on_surface)

        # ------------------------ emitter sampling ------------------------
        nee_medium = scattered & medium.use_emitter_sampling()
        nee_surface = on_surface & smooth
        active_em = active_next & (nee_medium | nee_surface)
        nee_ref, nee_beta, at_point = ref, beta, mi.Bool(False)
        if dr.hint(gd, mode="scalar"):   # the segment's guided point samples instead
            handled = gd_lanes & gd_point.valid
            at_point = handled & gd_point.used(scattered)
            active_em = (active_em & ~(scattered & handled)) | at_point
            nee_ref = mi.Interaction3f(ref)
            nee_ref.t[at_point], nee_ref.p[at_point] = gd_point.t, gd_point.p
            nee_ref.n[at_point] = mi.Normal3f(0.0)
            nee_beta = dr.select(at_point, gd_beta, beta)
        ds, em_weight = emitters.sample_direction(nee_ref, sampler.next_2d(), active_em,
                                                  test_visibility=False)
        active_em &= ds.pdf != 0
        if dr.hint("nee" not in settings.terms, mode="scalar"):
            active_em = mi.Bool(False)
        wo = si.to_local(ds.d)
        shadow_medium = dr.select(on_surface & si.is_medium_transition() & ~at_point,
                                  si.target_medium(ds.d), medium)
        if dr.hint(shadows is None, mode="scalar"):
            T = shadow_transmittance(scene, media, nee_ref, ds, shadow_medium, sampler,
                                     ctx.estimator, active_em, integrator.shadow_roulette)
        else:
            # a gradient render: the replay reads what the primal pass estimated
            from_store = (active_em & shadows.stored(event)) if replay is not None \
                else mi.Bool(False)
            T = shadow_transmittance(scene, media, nee_ref, ds, shadow_medium,
                                     shadows.numbers(event), ctx.estimator, active_em & ~from_store,
                                     integrator.shadow_roulette)
            if dr.hint(replay is None, mode="scalar"):
                shadows.put(event, T, active_em)
            else:
                T = dr.select(from_store, shadows.get(event, from_store), T)
        if dr.hint(eq, mode="scalar"):   # the vertex's share of the two (balance heuristic)
            T *= equiangular.free_flight_weight(ray, si.t, eq_sigma_t, t_s, ds,
                                                eq_lanes & scattered)

        # ---------------------- BSDF or phase sampling ----------------------
        u1 = sampler.next_1d()
        u2 = sampler.next_2d()
        bsdf_val, p_b, bs, bsdf_weight = bsdf.eval_pdf_sample(bsdf_ctx, si, wo, u1, u2,
                                                               on_surface)
        in_medium = scattered | at_point                 # the emitter sample's vertex
        phase_val, phase_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, in_medium)
        wo_phase, phase_weight, phase_pdf_s = phase.sample(phase_ctx, mei, u1, u2, scattered)
        if dr.hint(guided, mode="scalar"):
            wo_phase, phase_weight, phase_pdf_s, f_wo, g = resample(
                guide.field, phase, phase_ctx, mei, sampler, guide.candidates,
                (wo_phase, phase_weight, phase_pdf_s),
                scattered & still_guided(gain), guide.symmetric, guide.lobe, depth)
        elif dr.hint(recording, mode="scalar"):
            f_wo = mi.Float(dr.mean(mi.Spectrum(phase_weight))) * phase_pdf_s
        f_l = dr.select(in_medium, mi.Spectrum(phase_val), mi.Spectrum(bsdf_val))
        p_dir = dr.select(in_medium, phase_pdf, p_b)
        if dr.hint(lamp_nee, mode="scalar"):   # MIS weight 1 toward a lamp
            p_dir = dr.select(at_point & guide.light.on_lamp(ds.p), 0.0, p_dir)
        nee = emitter_contribution(integrator.mis, si, ds, em_weight * T, wo, f_l, p_dir)
        L_pre = L
        L = dr.select(active_em, dr.fma(nee_beta, nee, L), L)
        if dr.hint(gd, mode="scalar"):
            # a segment that passed through the medium gathered light: the pixel saw it
            valid_ray |= at_point
        if dr.hint(learn_light, mode="scalar"):
            recorded = (nee_medium & active_next & ~handled) | at_point if gd \
                else nee_medium & active_next
            if dr.hint(ctx.drawn is not None, mode="scalar"):   # dense homogeneous media not
                in_homogeneous = (medium != None) & medium.is_homogeneous()  # noqa: E711
                recorded &= guide.light.takes(in_homogeneous, ctx.drawn[2])
            guide.light.record(nee_ref.p, dr.select(active_em, nee, 0.0), recorded)
        if dr.hint(replay is not None, mode="scalar"):
            def vertex_value(d_world, wo_local):
                """The phase (medium) or BSDF (surface) value towards a direction, as a
                function: replay_vertex evaluates it attached, when it needs it."""
                return lambda: dr.select(scattered, mi.Spectrum(phase.eval_pdf(
                    phase_ctx, mei, d_world, scattered)[0]), bsdf.eval(
                        bsdf_ctx, si, wo_local, on_surface))
            grad += replay_vertex(
                replay, scene, media, ref, ds, shadow_medium,
                dr.select(active_em, beta * emitter_contribution(
                    integrator.mis, si, ds, em_weight * T, wo, f_l, p_dir), 0.0),
                vertex_value(ds.d, wo), active_em, vertex_value(wo_phase, bs.wo),
                replay.L_primal - L, active_next & (scattered | (on_surface & ~mi.has_flag(
                    bs.sampled_type, mi.BSDFFlags.Delta))))

        if dr.hint(recording, mode="scalar"):
            records = records.add(guide.field, mei.p, wo_phase, L, beta, f_wo,
                                  sampler.next_1d(), scattered & active_next, L_pre)

        # ------------------------- throughput update -------------------------
        null = on_surface & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
        real = scattered | (on_surface & ~null)
        bsdf_weight = si.to_world_mueller(bsdf_weight, -bs.wo, si.wi)
        beta[on_surface] *= bsdf_weight
        beta[scattered] *= phase_weight
        eta[on_surface] *= bs.eta
        ray[on_surface] = si.spawn_ray(si.to_world(bs.wo))
        ray[scattered] = mei.spawn_ray(wo_phase)
        medium[on_surface & si.is_medium_transition()] = si.target_medium(ray.d)
        valid_ray |= real
        prev_si[real] = ref
        prev_pdf[real] = dr.select(scattered, phase_pdf_s, bs.pdf)
        prev_delta[real] = dr.select(scattered, ~nee_medium,
                                     mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta))
        if dr.hint(lamp_nee, mode="scalar"):
            prev_point[real] = scattered & handled

        # ------------------------- Russian roulette -------------------------
        depth[real] += 1
        count("medium_vertices", scattered)
        count("surface_vertices", on_surface & ~null)
        count("shadow_rays", active_em)
        if dr.hint(guided, mode="scalar"):
            gain[scattered] *= g
        beta, alive = integrator.rr.apply(beta, eta, depth, sampler.next_1d(), real,
                                          gain=gain if guided else None)
        if dr.hint(steered, mode="scalar"):
            rr_ref, beta, kept = roulette(guide.field, guide.roulette, rr_ref, mei.p, beta,
                                          sampler.next_1d(), scattered & alive, gain)
            alive &= kept

        # ------------------------------ advance ------------------------------
        if dr.hint(shadows is not None, mode="scalar"):
            event += 1
        active = alive & (real | null) & (depth < max_depth)
        active &= ~(scattered & (phase_pdf_s <= 0))
        if dr.hint(empty is not None, mode="scalar"):
            # a path that ends goes on as the sub-path of its kept point
            go = empty.restart(active, L, valid_ray, grad)
            ray[go] = mi.Ray3f(empty.p, empty.d, ray.time, ray.wavelengths)
            medium[go] = empty.medium
            depth[go] = empty.depth
            beta[go], r_u[go], eta[go], L[go] = 1.0, 1.0, 1.0, 0.0
            prev_delta[go] = True
            forced |= go
            active |= go
            if dr.hint(shadows is not None, mode="scalar"):
                event[go] = SUB_PATH_EVENT

    if dr.hint(replay is not None, mode="scalar"):
        if dr.hint(empty is not None, mode="scalar"):
            L_s, L, valid_ray, grad = empty.end(L, valid_ray, grad)
            replay.dL = dL_path
            grad += empty.finish(replay, media, L_s, mi.Bool(True))  # invalid lanes too
        # the tangent is not masked by valid_ray: a lane that saw nothing (emitters
        # hidden) may still carry a sub-path's in-scattering term
        return dr.select(valid_ray, L, 0.0), valid_ray, grad
    if dr.hint(recording, mode="scalar"):
        records.flush(guide.field, L, mi.Bool(True))
    return dr.select(valid_ray, L, 0.0), valid_ray
