"""Path tracer with next-event estimation, MIS and configurable Russian roulette."""
from __future__ import annotations

import mitsuba as mi

from mitsuba_plugins import guided_render
from mitsuba_plugins.guiding.field import BINS, check_memory
from mitsuba_plugins.path_loop import PathIntegrator
from mitsuba_plugins.path_vertex import EMITTER_SELECTIONS, RR_RULES, RussianRoulette
from mitsuba_plugins.validity import refuse_gradients

#: default guiding_fraction, chosen on the tuning room (docs/benchmarks.md)
FRACTION = 0.2
#: default guiding_portal, chosen on the tuning room (guiding.field.PORTAL_ROWS)
PORTAL = 0.1

VARIANT = mi.variant()


class PathRR(PathIntegrator):
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
       - ``throughput``: survival ``clamp(max(beta) * eta^2, rr_min_survival, rr_max_survival)``
         (Mitsuba's rule when ``rr_min_survival = 0``); ``fixed``: survival
         ``rr_survival`` at every vertex. (Default: ``throughput``)
     * - rr_survival
       - |float|
       - Survival probability of the ``fixed`` rule, in (0, 1]. (Default: 0.95)
     * - rr_min_survival
       - |float|
       - Lower clamp of the ``throughput`` rule, in [0, rr_max_survival]: bounds the weight 1/s a
         surviving path can gain (fewer fireflies). (Default: 0)
     * - rr_max_survival
       - |float|
       - Upper clamp of the ``throughput`` rule, in (0, 0.9999]. (Default: 0.95, Mitsuba's)
     * - emitter_selection
       - |string|
       - ``uniform`` (Mitsuba's) or ``power`` (proportional to emitted flux). (Default: ``uniform``)
     * - guiding
       - |string|
       - Path guiding at surfaces (docs/method.md section 13): ``off``, or ``surfaces``:
         at surfaces without delta or transmissive lobes, directions from a one-sample MIS
         mixture of the BSDF and a field learnt during the render (a grid of cells, one
         directional histogram each), within one ``mi.render`` call; unguided after the
         first pass where it finds under 0.3 of the light beyond the paths' first direct
         light (docs/method.md section 13). (Default: ``off``)
     * - guiding_fraction
       - |float|
       - Probability of sampling the learnt distribution where a cell has one, in
         [0, 0.9]. (Default: 0.2)
     * - guiding_training
       - |float|
       - Largest share of the samples spent in training passes, in [0, 0.9].
         (Default: 0.25)
     * - guiding_resolution
       - |int|
       - Cells per axis of the guiding field over the scene's bounds, in [1, 32].
         (Default: 8)
     * - guiding_bins
       - |int|
       - Directions per cell: a histogram of ``guiding_bins``^2 equal-area bins over the
         sphere, in [0, 64]; 0: one von Mises-Fisher lobe per cell. (Default: 16)
     * - guiding_nee
       - |bool|
       - With ``guiding``: each cell of the field also learns, per side a surface faces,
         the squared light its emitter samples bring (relative to their pixels) against
         the paths' whole squared light, and a vertex there samples an emitter with the
         probability that minimises variance times time, in [0.05, 1] (weighted by its
         inverse, and in the MIS weights; docs/method.md section 13).
         (Default: true)
     * - guiding_portal
       - |float|
       - With ``guiding``: the share of a guided vertex's directions drawn toward a
         point of its cell's learnt portal, in [0, 0.5]: an axis-aligned rectangle that
         most of the recorded light of its neighbourhood crossed (a door, a hole), found
         from the training passes' records; its density enters the mixture's pdf
         (docs/method.md section 13). 0: none. (Default: 0.1)
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

    NAME = "path_rr"
    PARAMETERS = ("rr_rule", "rr_survival", "rr_min_survival", "emitter_selection",
                  "guiding", "guiding_fraction", "guiding_training", "guiding_resolution",
                  "guiding_bins", "guiding_nee", "guiding_portal")

    def configure(self, p):
        self.rr = RussianRoulette(
            rr_depth=self.rr.rr_depth,
            rule=p.choice("rr_rule", "throughput", RR_RULES),
            survival=p.float("rr_survival", 0.95, lo=0.0, hi=1.0, lo_open=True),
            min_survival=p.float("rr_min_survival", 0.0, lo=0.0, hi=self.rr.max_survival),
            max_survival=self.rr.max_survival)
        self.emitter_selection = p.choice("emitter_selection", "uniform", EMITTER_SELECTIONS)
        guided_render.configure(self, p, ("surfaces",), resolution=8)
        self.guiding_fraction = p.float("guiding_fraction", FRACTION, lo=0.0, hi=0.9)
        self.guiding_bins = p.int("guiding_bins", BINS, lo=0, hi=64)
        self.guiding_nee = p.bool("guiding_nee", True)
        self.guiding_portal = p.float("guiding_portal", PORTAL, lo=0.0, hi=0.5)
        check_memory(self.guiding_resolution, self.guiding_bins)

    def to_string(self):
        return (f"PathRR[\n  max_depth = {self.max_depth},\n  roulette = {self.rr},\n"
                f"  emitter_selection = {self.emitter_selection},\n"
                f"  hide_emitters = {self.hide_emitters}\n]")


mi.register_integrator("path_rr", guided_render.factory(PathRR))
