"""Unbiased volumetric path tracer: analytic free flight in homogeneous media, delta
tracking on a majorant grid in heterogeneous ones, spectral MIS, NEE with MIS."""
from __future__ import annotations

import mitsuba as mi

from mitsuba_plugins import differentiable, guided_render
from mitsuba_plugins.tracking.free_flights import FREE_FLIGHTS
from mitsuba_plugins.tracking.replay import GRADIENT_ESTIMATORS
from mitsuba_plugins.tracking.scene_media import SceneMedia
from mitsuba_plugins.tracking.transmittance import TRANSMITTANCE_ESTIMATORS
from mitsuba_plugins.tracking.walk import walk
from mitsuba_plugins.volume_loop import VolumeStrategy, VolumetricIntegrator

VARIANT = mi.variant()

#: Defaults chosen on the dense-media family (issue 16, benchmarks/results/dense.md):
#: residual-ratio-tracked shadow rays and the roulette's survival capped at 0.99.
DEFAULT_TRANSMITTANCE = "residual"
DEFAULT_FREE_FLIGHT = "delta"
#: Chosen on the tuning half of the held-out dense family (issue 29,
#: its table: git show aa26248:benchmarks/results/dense_heldout_tuning.md).
DEFAULT_SHADOW_ROULETTE = 0.2
#: Largest threshold: below 1, so that an unattenuated ray is never played.
MAX_SHADOW_ROULETTE = 0.999
#: Chosen on benchmarks/results/inverse.md: ``sm`` (where it applies) reconstructs the
#: smoke faster than ``drt`` ("Which estimator reconstructs faster").
DEFAULT_GRADIENT_ESTIMATOR = "auto"


class VolpathDelta(VolumetricIntegrator):
    r"""
    .. _integrator-volpath_delta:

    Delta-tracking volumetric path tracer (:monosp:`volpath_delta`)
    ---------------------------------------------------------------

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path depth (-1 = unbounded). Depth counts real scattering in media and
         non-null surface events, as in Mitsuba's ``volpath``. (Default: -1)
     * - rr_depth
       - |int|
       - Depth (>= 1) at which Russian roulette starts. (Default: 5)
     * - rr_max_survival
       - |float|
       - Cap of the roulette's survival probability ``min(max(beta) eta^2, cap)``, in
         (0, 0.9999]. Mitsuba's 0.95 makes path weights grow by albedo / 0.95 per
         vertex in media of albedo > 0.95 (heavy-tailed); 0.99 was measured best on the
         dense family. (Default: 0.99)
     * - free_flight
       - |string|
       - Free-flight estimator in heterogeneous media: ``delta`` (delta tracking) or
         ``decomposition`` (decomposition tracking, Kutz et al. 2017: the majorant
         grid's per-cell minorant as a control collided on its own clock, the residual
         delta-tracked; the same estimator with fewer lookups where the minorant is
         large). (Default: ``delta``)
     * - transmittance
       - |string|
       - Shadow-ray transmittance estimator in heterogeneous media: ``ratio`` (ratio
         tracking with roulette below 0.1), ``residual`` (residual ratio tracking, the
         majorant grid's per-cell minorant as control) or ``track_length``.
         (Default: ``residual``)
     * - shadow_roulette
       - |float|
       - Russian roulette between the pieces of a shadow ray (medium to medium through
         ``null`` surfaces), in [0, 1): where the transmittance so far ``T`` is below
         this threshold, the ray goes on with probability ``max(T) / threshold`` and
         weight ``1 / p``; 0 turns it off. Unbiased; in dense media it ends most shadow
         rays at the medium's boundary instead of tracing them on to the light.
         (Default: 0.2)
     * - equiangular
       - |bool|
       - Also sample distances toward point and spot lights (equiangular sampling,
         Kulla and Fajardo 2012), combined with free-flight sampling by the balance
         heuristic, in homogeneous media of gray extinction. Pays where lights sit
         inside a thin medium (1.7-2.4x the efficiency without it in a fog cube of
         optical depth 0.6-2 across, docs/benchmarks.md); costs time in dense media
         lit from outside, hence off. Primal renders only. (Default: false)
     * - gradient_estimator
       - |string|
       - How derivatives of transmittance are estimated in gradient renders
         (``mi.render`` with differentiable parameters): ``drt`` (differential
         tracking: minus the optical depth's derivative at points of a second random
         stream, Nimier-David et al. 2022) or ``delta`` (differentiate the
         delta-tracking estimator as ``prbvolpath`` does: null collisions weigh
         ``sigma_n(theta) / sigma_n``) or ``sm`` (sample matching: on the camera's
         flights the light a denser medium would scatter and the light it would block,
         both at one point per path, one sub-path for the first; lower variance, gray,
         non-emitting media only) or ``auto``: ``sm`` where the scene's heterogeneous
         media are gray and emit nothing, else ``drt`` (``sm`` reaches ``drt``'s final
         loss in about a third of the time on a smoke reconstruction,
         docs/benchmarks.md). Primal renders do not use it. (Default: ``auto``)
     * - guiding
       - |string|
       - Path guiding (docs/method.md section 13): ``off``, or ``volumes``: scattering
         directions in media resampled among phase-function samples in proportion to a
         field learnt during the render (a grid of cells, one von Mises-Fisher lobe
         each), within one ``mi.render`` call (training passes, then the rest of the
         samples guided; unguided where the first pass finds under 0.3 of the light
         beyond the paths' first direct light). Primal renders only. (Default: ``off``)
     * - guiding_candidates
       - |int|
       - Phase-function samples among which a guided vertex resamples its direction in
         proportion to the learnt incident radiance, in [1, 32]. (Default: 4)
     * - guiding_lobe
       - |int|
       - More candidates, drawn from the learnt lobe itself, where a cell's lobe is
         concentrated, at a path's first 3 vertices (weights by the balance heuristic
         over both densities), in [0, 32]. Pays where light reaches a forward-scattering
         medium from outside the phase function's cone; costs time elsewhere (the test
         set's scenes: +2-8% per sample, no gain). (Default: 0)
     * - guiding_training
       - |float|
       - Largest share of the samples spent in training passes, in [0, 0.9].
         (Default: 0.25)
     * - guiding_resolution
       - |int|
       - Cells per axis of the guiding field over the media's bounds, in [1, 32].
         (Default: 4)
     * - guiding_roulette
       - |float|
       - Roulette by the learnt radiance in guided passes: a path whose throughput times
         the learnt fluence where it scatters falls below this share of what it was at
         its first medium vertex survives with probability (share / this), at least
         0.05, in [0, 1]; 0: none. (Default: 0: since guided passes' roulette follows
         the unguided throughput it no longer pays, docs/benchmarks.md)
     * - guiding_distance
       - |bool|
       - In guided passes, take each segment's emitter sample in a homogeneous medium of
         gray extinction at a point drawn toward where the learnt once-scattered light
         is, not at the free-flight vertex (docs/method.md section 13). (Default: true)
     * - hide_emitters
       - |bool|
       - Hide emitters seen directly (also through media). (Default: false)

    A replacement for Mitsuba's ``volpath`` (same parameters and meanings) that estimates
    the same image with less variance per unit time:

    * homogeneous media: analytic free-flight sampling with the channel-averaged pdf
      (docs/method.md section 7) and analytic shadow transmittance ``exp(-sigma_t d)``;
    * heterogeneous media: delta tracking against the majorant grid of ``grid_medium``
      (the global majorant for other media), null-scattering formulation with spectral
      MIS over the hero channel for chromatic extinction (Miller, Georgiev and Jarosz
      2019); see :class:`mitsuba_plugins.tracking.free_flights.DeltaTracking`;
    * emissive ``grid_medium``: :math:`\sigma_a L_e` collected at tentative collisions;
    * Russian roulette (Mitsuba's throughput rule, survival capped at ``rr_max_survival``)
      once per real event, never at null collisions; MIS (power heuristic) between emitter and phase/BSDF sampling using
      the directional pdfs, the transmittance being estimated in both;
    * a camera inside a medium (the sensor's ``medium``) is supported.

    Each render inspects the scene and traces only the code it needs: without media it
    runs the ``path_rr`` kernel; without heterogeneous media there is no tracking loop;
    gray extinction has no spectral MIS; media without emission no emission code.

    Estimator for a path :math:`\bar x` sampled with hero channel :math:`h`:

    .. math::

        \langle L\rangle_c = \frac{f_c(\bar x)}{\frac1n\sum_{k} p_k(\bar x)}
                           = \frac{\beta_c}{\mathrm{mean}(r_u)},\qquad
        r_{u,k} = \frac{p_k(\bar x)}{p_h(\bar x)},

    where :math:`p_k` is the pdf of the path had channel :math:`k` made the
    real/null decisions (Miller et al. 2019, eq. 24).
    """

    NAME = "volpath_delta"
    PARAMETERS = ("transmittance", "free_flight", "gradient_estimator", "shadow_roulette",
                  "equiangular", "guiding", "guiding_candidates", "guiding_training",
                  "guiding_resolution", "guiding_roulette", "guiding_distance", "guiding_lobe")
    RR_MAX_SURVIVAL = 0.99

    def configure(self, p):
        self.transmittance = p.choice("transmittance", DEFAULT_TRANSMITTANCE,
                                      tuple(TRANSMITTANCE_ESTIMATORS))
        self.free_flight = p.choice("free_flight", DEFAULT_FREE_FLIGHT, tuple(FREE_FLIGHTS))
        self.shadow_roulette = p.float("shadow_roulette", DEFAULT_SHADOW_ROULETTE, lo=0.0,
                                       hi=MAX_SHADOW_ROULETTE)
        self.equiangular = p.bool("equiangular", False)
        self.gradient_estimator = p.choice("gradient_estimator", DEFAULT_GRADIENT_ESTIMATOR,
                                           ("auto", *GRADIENT_ESTIMATORS))
        guided_render.configure(self, p, ("volumes",), guided_render.RESOLUTION)
        self.guiding_candidates = p.int("guiding_candidates", guided_render.CANDIDATES, lo=1,
                                        hi=32)
        self.guiding_lobe = p.int("guiding_lobe", guided_render.LOBE, lo=0, hi=32)
        self.guiding_roulette = p.float("guiding_roulette", guided_render.ROULETTE, lo=0.0,
                                        hi=1.0)
        self.guiding_distance = p.bool("guiding_distance", True)
        self.strategy = TrackingStrategy(FREE_FLIGHTS[self.free_flight],
                                         TRANSMITTANCE_ESTIMATORS[self.transmittance])

    def to_string(self):
        return (f"VolpathDelta[\n  max_depth = {self.max_depth},\n  roulette = {self.rr},\n"
                f"  free_flight = {self.free_flight},\n"
                f"  transmittance = {self.transmittance},\n"
                f"  shadow_roulette = {self.shadow_roulette:g},\n"
                f"  equiangular = {self.equiangular},\n"
                f"  gradient_estimator = {self.gradient_estimator},\n"
                f"  guiding = {self.guiding},\n"
                f"  hide_emitters = {self.hide_emitters}\n]")


    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        return differentiable.render_forward(self, scene, params, sensor, seed, spp)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        return differentiable.render_backward(self, scene, params, grad_in, sensor, seed, spp)

    def check_gradients(self) -> None:
        """Refuse gradient renders of settings whose derivatives are not implemented."""
        if self.equiangular:
            raise NotImplementedError(
                "volpath_delta: gradients need equiangular = false; the primal image is "
                "the same estimate")
        if self.guiding != "off":
            raise NotImplementedError(
                f"volpath_delta: gradients need guiding = 'off' (got '{self.guiding}'); "
                "guided directions are not replayed")
        if self.free_flight != "delta":
            raise NotImplementedError(
                f"volpath_delta: gradients need free_flight = 'delta' (got "
                f"'{self.free_flight}'); the primal image is the same estimate")


class TrackingStrategy(VolumeStrategy):
    """The medium phase of ``volpath_delta``: analytic flights in homogeneous media (the
    base's), the ``flight`` rule (an entry of
    :data:`~mitsuba_plugins.tracking.free_flights.FREE_FLIGHTS`) in heterogeneous ones, shadow rays
    by ``estimator``."""

    def __init__(self, flight, estimator):
        self.flight, self.estimator = flight, estimator

    def shadow_estimator(self, media: SceneMedia):
        return self.estimator

    def heterogeneous_flight(self, ctx, tracker, ray, t_max, beta, r_u, nee, active):
        media = ctx.media
        rule = self.flight(beta, r_u, ctx.hero, media.chromatic_heterogeneous, media.emission,
                           ctx.replay, ctx.remaining)
        return walk(tracker, ray, t_max, ctx.sampler, rule, active)


mi.register_integrator("volpath_delta", guided_render.factory(VolpathDelta))
