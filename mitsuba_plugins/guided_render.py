"""One guided render of ``volpath_delta`` (``guiding = volumes``) or ``path_rr`` (``guiding
= surfaces``): passes that learn where light comes from and then guide, all inside one
``mi.render`` call (docs/method.md section 13).

The schedule: training passes of doubling sample counts (from ``spp / 128``, at least 1)
while their sum stays within ``guiding_training`` of ``spp``, then one pass with the rest;
one plain pass where that training budget is below :data:`MIN_TRAINING_PATHS` paths.
Where the first pass finds that little of the light lies beyond the paths' first vertex's
direct light (:data:`MIN_SHARE`), the rest of the samples are one plain pass.
The first pass samples the phase function (or BSDF) alone; every pass records its medium
(or surface) vertices into the field except the last; the field is fixed within a pass (folded in between), so
each pass is an unbiased estimate. The guided passes are combined in proportion to their
sample counts, and the first pass, which guides nothing, only trains: fixed weights, so
the combination is unbiased too (weights from the passes' measured variances would
favour the guided passes but depend on the data). Its samples are max(1, spp / 128)
of the render's (1/64 at 64 spp, 1/128 from 128 spp); with weight, the tuning set's
lamp ball had 7% more variance per sample (pass 1: 14.1 relMSE per sample; the guided
passes: 2.6-3.2).

Each pass is Mitsuba's own Python render of an ``ADIntegrator`` (film, rays, one wavefront),
so a guided render never re-enters the C++ ``SamplingIntegrator.render`` from Python.
"""
from __future__ import annotations

import time

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins.guiding import distance
from mitsuba_plugins.guiding.field import (GuidingField, HistogramField, geometry_planes,
                                           media_bounds, scene_bounds)
from mitsuba_plugins.tracking.scene_media import SceneMedia, scene_media

_common = mi.ad.integrators.common
VARIANT = mi.variant()

#: defaults of volpath_delta's guiding_candidates, guiding_training, guiding_resolution
CANDIDATES = 4
TRAINING = 0.25
RESOLUTION = 4
#: default of volpath_delta's guiding_lobe: resampling candidates drawn from the learnt
#: distribution itself, beside the phase function's (guiding.sampling.resample). 1 won on
#: the tuning set (forward_lamp 3.08x -> 4.01x against volpath at 64 spp, its heavy tail
#: gone at 256 spp; the others -3% to +1%) but not on the test set: the cloud 2.79x ->
#: 2.71x at 64 spp and 2.85x -> 2.84x at 256, the HG 0.9 ball 2.60x -> 2.60x and 2.92x
#: -> 2.87x (variance per sample -8 to -10%, time per sample +10 to +13%:
#: docs/benchmarks.md, seventh session). Only at a path's first 3 vertices
#: (guiding.sampling.LOBE_DEPTH, chosen on the tuning set after that): the cloud 2.72x ->
#: 2.71x and 2.91x -> 2.85x, the ball 2.73x -> 2.69x and 2.99x -> 3.01x. So 0
LOBE = 0
#: default of volpath_delta's guiding_roulette (guiding.sampling.roulette)
ROULETTE = 0.0


class GuidedPass:
    """What one pass hands the path loop: the ``field`` (None before it has learnt
    anything), whether it samples from it and whether it records into it."""

    def __init__(self, field, sampling: bool, recording: bool, candidates: int = 1,
                 fraction: float = 0.0, roulette: float = 0.0, light=None,
                 symmetric: bool = False, media=None, lobe: int = 0, nee: bool = False,
                 portal: float = 0.0):
        self.field, self.sampling, self.recording = field, sampling, recording
        # share of a guided surface vertex's choice drawn toward its cell's learnt
        # portal (path_rr's guiding_portal, HistogramField.portals)
        self.portal = portal
        # sampling passes take emitter samples with the field's learnt probability
        # (path_rr's guiding_nee, GuidingField.nee_probabilities)
        self.nee = nee
        # per pixel, one over its squared value as the passes so far estimate it
        # (pixel_weights; None in the first pass), and per lane of the pass (set by the
        # pass before it traces: _PassRender.sample)
        self.pixel_weight, self.lane_weight = None, None
        self.candidates, self.fraction, self.roulette = candidates, fraction, roulette
        self.lobe = lobe           # resampling candidates drawn from the field itself
        self.light = light         # guiding.distance.LightGrid, or None
        # every phase function is symmetric about the incident direction (no microflake):
        # resampling's candidates may be turned about it (guiding.sampling.resample)
        self.symmetric = symmetric
        # the render's SceneMedia, derived once for all its passes (None: each pass derives
        # it; reading chromatic extinction back costs a kernel launch and a wait)
        self.media = media


class _PassRender:
    """What ``ADIntegrator.render`` calls on ``self``, for one pass."""
    prepare = _common.ADIntegrator.prepare
    sample_rays = _common.ADIntegrator.sample_rays
    render = _common.ADIntegrator.render

    def __init__(self, integrator, sensor: mi.Sensor, guide: GuidedPass):
        self.integrator, self.sensor, self.guide = integrator, sensor, guide

    def aov_names(self):
        return []

    def sample(self, mode, scene, sampler, ray, active=True, **kwargs):
        guide = self.guide
        if guide is not None and guide.recording and guide.pixel_weight is not None:
            # lane i traces pixel i // spp (ADIntegrator.sample_rays)
            pixel = dr.arange(mi.UInt32, dr.width(ray.o)) // sampler.sample_count()
            guide.lane_weight = dr.gather(mi.Float, guide.pixel_weight, pixel)
        # the plugin's own sample (its loop: surfaces or volumes), with this pass's guide
        L, valid, _ = self.integrator.sample(scene, sampler, ray, self.sensor.get_medium(),
                                             mi.Bool(active), guide=self.guide)
        return L, valid, [], None


#: paths the training passes must trace together for a render to be guided: a pass costs
#: a few milliseconds beside its paths (Python traces its loop, its kernels launch, the
#: records are folded in; 5-7 ms on the 2-core EPYC), which at 32x32 and 64 spp took most
#: of a guided render's time (the dense family's cube pairs: 35 spp against 79 unguided in
#: the same time). Below it: one plain pass. First 2^18 (128x128 at 64 spp just guided):
#: a benchmark at equal time then rendered the gap room at 63 spp, unguided. With a pass's
#: tracing halved (loop_state.widened), the tuning set, guided over unguided efficiency
#: (6 renders each): 128x128 at 32 spp (2^17) gap room 1.60, lamp ball 2.56, forward lamp
#: 1.81, dense ball 0.93; 64x64 at 64 spp (2^16) 1.51, 2.42, 1.53, 1.01; 32x32 at 64 spp
#: (2^14) 1.26, 1.89, 1.65, 0.85. So 2^16: 64x64 at 64 spp and 128x128 from 16 spp are
#: guided, 32x32 at 64 spp (the dense family's size) is not.
MIN_TRAINING_PATHS = 1 << 16

#: paths each pass after the first must trace, per Dr.Jit backend: on a GPU a pass's
#: paths cost so little that its fixed cost decides. Measured on an NVIDIA H200
#: (cuda_ad_rgb, the camera inside the cloud at 128x128): a pass costs about 6 ms beside
#: its paths (tracing in Python, launches, folding records in) against 0.2 ms per sample
#: per pixel (16,384 paths), so the default schedule of five passes (1, 2, 4, 8, 49 spp at
#: 64 spp) spent most of a guided render on them: 47 spp in the time unguided rendered 223
#: (docs/benchmarks.md, "Guiding on a GPU"). From 2^21 paths a pass's paths cost several
#: times its fixed cost. On the LLVM backend (~50x slower per path) the same holds for
#: small images: at 32x32 a pass costs about 6 ms beside its paths, as much as 2-10 spp of
#: the dense family's scenes. 2^15 was chosen on the dense family's tuning half (32x32, 256
#: spp: passes 2, 32, 222 instead of 2, 4, 8, 16, 32, 194), guided efficiency over no
#: floor, 8 renders each at equal spp: the six grids 1.03-1.13 (median 1.08), the six
#: homogeneous scenes 0.92-1.61 (median 1.00); the volume tuning set at 64x64 and 64 spp
#: (1, 8, 55 spp): 0.92-1.06 (median 1.05). From 128x128 at 64 spp it changes nothing
#: (docs/benchmarks.md, nineteenth session).
MIN_PASS_PATHS = {"cuda": 1 << 21, "llvm": 1 << 15}


#: the share of a path's light that guided directions can change, below which a render
#: goes on unguided after its first pass: what the paths of that pass gathered beyond
#: their first vertex's direct light (its emitter sample and whatever its sampled
#: direction hit directly), over all they gathered (``GuidingField.flow``). Guiding
#: changes only that share; if its variance went with its light, even a guide that
#: removed all of it would not pay back a guided pass's extra time per sample c below a
#: share of 1 - 1/c. c = 1.42, the median over the volume tuning set (guided spp against
#: unguided in the same time, docs/benchmarks.md), gives 0.3. Measured shares (128x128,
#: first pass): volume tuning set 0.37 (forward_lamp) to 0.81 (dense ball), none skipped;
#: surfaces' tuning room 1.0. A first pass that found no light at all counts as 0.
MIN_SHARE = 0.3


def schedule(spp: int, training: float, pixels: int = 1 << 30, min_pass: int = 1) -> list:
    """Sample counts of the passes: doubling training passes, then the rest; ``pixels``:
    the paths of one sample per pixel (:data:`MIN_TRAINING_PATHS`). The passes after
    the first hold at least ``min_pass`` samples per pixel (:data:`MIN_PASS_PATHS`):
    doubling steps below it merge into one pass, or, where even one such pass does not
    fit the training budget, the first pass alone trains."""
    if training * spp * pixels < MIN_TRAINING_PATHS:
        return [spp]
    passes, spent, n = [], 0, max(1, spp // 128)
    while spent + n <= training * spp and spent + n < spp:
        passes.append(n)
        spent += n
        n = max(2 * n, min_pass)
    return passes + [spp - spent]


def min_pass_spp(pixels: int) -> int:
    """The ``min_pass`` of :func:`schedule` on this variant's backend."""
    backend = "cuda" if dr.backend_v(mi.Float) == dr.JitBackend.CUDA else "llvm"
    return max(1, -(-MIN_PASS_PATHS[backend] // max(pixels, 1)))


class GuidingReport:
    """What the last guided render did (for benchmarks and ``to_string``)."""

    def __init__(self):
        self.passes, self.training_seconds, self.cells_guided, self.memory = [], 0.0, 0, 0
        # the first pass's share of light beyond the first vertex's direct light
        # (:data:`MIN_SHARE`), and whether the render went on unguided for it
        self.share, self.skipped = None, False
        self.field = None      # the field learnt (None without training passes)
        self.light = None      # the light grid learnt (guiding_distance)


#: :func:`pixel_weights`: the box filter's radius (pixels) and the floor, a share of the
#: image's mean, under which a pixel's smoothed value does not fall
PIXEL_RADIUS = 2
PIXEL_FLOOR = 0.05


def pixel_weights(image: np.ndarray) -> mi.Float:
    """Per pixel (row-major), ``1 / v^2`` with ``v`` its value (channels averaged) in the
    passes' ``image`` so far, smoothed by a box of side ``2 PIXEL_RADIUS + 1`` and at least
    ``PIXEL_FLOOR`` times the image's mean: a path's squared light over this weighs it
    as relMSE weighs its pixel's error (``GuidingField.record_nee``). The box and the
    floor keep a noisy or black pixel of a few samples from weighing thousands of
    times its neighbours; a black image weighs every pixel 1."""
    lum = np.asarray(image, np.float64)
    if lum.ndim == 3:        # RGB (and alpha) or a value (and alpha)
        lum = lum[..., :3 if lum.shape[-1] >= 3 else 1].mean(axis=-1)
    lum = np.where(np.isfinite(lum), lum, 0.0)
    if not lum.mean() > 0:            # no light seen yet: every pixel alike
        return mi.Float(np.ones(lum.size, np.float32))
    r = PIXEL_RADIUS
    padded = np.pad(lum, r, mode="edge")
    c = np.cumsum(np.cumsum(np.pad(padded, ((1, 0), (1, 0))), axis=0), axis=1)
    k = 2 * r + 1
    box = (c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]) / (k * k)
    v = np.maximum(box, PIXEL_FLOOR * lum.mean())
    return mi.Float((1.0 / (v * v)).ravel().astype(np.float32))


def _pass_seed(seed, k: int) -> int:
    """The seed of pass ``k > 0``: TEA of the render's seed and ``k``, on the host where
    the seed is a Python integer (the vector overload launches a kernel and waits)."""
    if isinstance(seed, int):
        return mi.sample_tea_32(seed & 0xFFFFFFFF, k)[0]
    return int(mi.sample_tea_32(mi.UInt32(seed), mi.UInt32(k))[0][0])


def render(integrator, scene: mi.Scene, sensor=0, seed=0, spp: int = 0) -> mi.TensorXf:
    """The guided render (see the module's docstring)."""
    if isinstance(sensor, int):
        sensor = scene.sensors()[sensor]
    if spp == 0:
        spp = sensor.sampler().sample_count()
    report = integrator.guiding_report = GuidingReport()
    size = sensor.film().crop_size()
    pixels = int(size[0]) * int(size[1])
    plan = schedule(spp, integrator.guiding_training, pixels, min_pass_spp(pixels))
    surfaces = integrator.guiding == "surfaces"
    media_needs = None if surfaces else SceneMedia(scene)
    if (not surfaces and not media_needs.any) or len(plan) == 1:
        # nothing to guide (no medium), or too few samples to learn from: one plain pass
        report.passes = [spp]
        return _PassRender(integrator, sensor, None).render(scene, sensor, seed, spp)
    bounds = scene_bounds(scene) if surfaces else media_bounds(scene)
    bins = getattr(integrator, "guiding_bins", 0)
    field = HistogramField(bounds, integrator.guiding_resolution, bins) if bins else \
        GuidingField(bounds, integrator.guiding_resolution)
    if bins and getattr(integrator, "guiding_portal", 0.0) > 0:
        field.geometry_planes = geometry_planes(scene)      # the portals' candidates
    media = scene_media(scene)
    g = distance.common_hg(media) or None
    light = distance.LightGrid(bounds, lamps=distance.lamps(scene, bounds, outside=g is not None),
                               lamp_boxes=distance.lamps(scene, bounds, boxes=True),
                               phase_g=g) \
        if getattr(integrator, "guiding_distance", False) and not surfaces and \
        distance.worthwhile(media, bounds) else None
    symmetric = not any(mi.has_flag(m.phase_function().flags(),
                                    mi.PhaseFunctionFlags.Microflake) for m in media)
    report.memory = field.memory() + (light.memory() if light is not None else 0)
    report.field, report.light = field, light
    image, t0, k = None, time.perf_counter(), 0
    seen, seen_spp = None, 0     # every pass's image so far, for pixel_weights
    while k < len(plan):
        n, last = plan[k], k == len(plan) - 1
        if last:
            report.training_seconds = time.perf_counter() - t0
        guide = None if report.skipped else \
            GuidedPass(field, sampling=k > 0, recording=not last,
                       candidates=getattr(integrator, "guiding_candidates", 1),
                       lobe=getattr(integrator, "guiding_lobe", 0),
                       fraction=getattr(integrator, "guiding_fraction", 0.0),
                       roulette=getattr(integrator, "guiding_roulette", 0.0),
                       light=light, symmetric=symmetric, media=media_needs,
                       nee=getattr(integrator, "guiding_nee", False),
                       portal=getattr(integrator, "guiding_portal", 0.0))
        if guide is not None and guide.portal > 0 and not last and \
                hasattr(field, "keep_portal_records"):
            field.keep_portal_records()     # every training pass finds the portals anew
        if guide is not None and guide.nee and seen is not None:
            guide.pixel_weight = pixel_weights(seen / seen_spp)
        pass_seed = seed if k == 0 else _pass_seed(seed, k)
        img = _PassRender(integrator, sensor, guide).render(scene, sensor, pass_seed, n)
        if k > 0:        # the first pass only trains (module docstring)
            w = n / (spp - plan[0])
            image = img * w if image is None else image + img * w
        if not last:
            dr.eval(image)
            if guide is not None and guide.nee:
                seen = (0.0 if seen is None else seen) + np.asarray(img, np.float64) * n
                seen_spp += n
            report.cells_guided = field.update()
            if light is not None:
                light.update()
        report.passes.append(n)
        if k == 0:
            report.share = field.flow[0] / field.flow[1] if field.flow[1] > 0 else 0.0
            if report.share < MIN_SHARE:       # guiding cannot pay: the rest unguided
                report.skipped, plan = True, [n, spp - n]
        k += 1
    return image


def configure(integrator, p, modes: tuple, resolution: int) -> None:
    """Read the guiding parameters of a plugin (``guiding`` among ``off`` and ``modes``,
    ``guiding_training``, ``guiding_resolution``, default ``resolution``) into it."""
    integrator.guiding = p.choice("guiding", "off", ("off", *modes))
    integrator.guiding_training = p.float("guiding_training", TRAINING, lo=0.0, hi=0.9)
    integrator.guiding_resolution = p.int("guiding_resolution", resolution, lo=1, hi=32)


def factory(plugin):
    """The constructor to register for the plugin class ``plugin``: with ``guiding`` on, a
    subclass whose render is :func:`render` (a class of its own, so that the unguided
    plugin keeps Mitsuba's C++ render)."""
    class Guided(plugin):
        def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
            if not develop:
                raise ValueError(f"{self.NAME}: guiding renders develop the film "
                                 "(develop=True)")
            return render(self, scene, sensor, seed, spp)
    Guided.__name__ = Guided.__qualname__ = f"Guided{plugin.__name__}"

    def make(props: mi.Properties):
        guided = "guiding" in props and props["guiding"] != "off"
        return (Guided if guided else plugin)(props)
    return make
