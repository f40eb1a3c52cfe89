"""Guided distance sampling for next-event estimation in homogeneous media
(docs/method.md section 13).

Where the light that scatters once at a point is bright in a small part of a medium (a
beam through a gap, the neighbourhood of a small light), free flights seldom stop there,
and the few that do carry large emitter samples: the fireflies that dominate such scenes
(the 2% largest squared deviations carried 81-96% of the squared error of the guiding
benchmark's gap room, camera in a cloud and forward-scattering ball; 29% on the smoke).

:class:`LightGrid` learns, per cell of a grid over the media, the mean of what
next-event estimation gathered at the medium points that fell in it (free-flight
vertices in the first pass, guided points after it; per unit of throughput, zeros
included): where the once-scattered light is. Along each path segment
``[0, t_end]`` of a homogeneous medium of gray extinction ``sigma``, one point is drawn
with density proportional to ``sigma exp(-sigma t) D(t)``, ``D`` the grid's values at the
midpoints of :data:`PIECES` equal pieces of ``[0, min(t_end, MAX_OPTICAL_DEPTH /
sigma)]`` (the last piece reaching to ``t_end``; piecewise constant, and at least
:data:`DEFENSIVE` times its largest value), and the segment's emitter sample is taken
there instead of at the free-flight vertex (:func:`plan` says on which lanes and with
which weight). The path loop keeps one shadow ray per iteration: adding this point's
sample to the vertex's (balance heuristic over the two densities, as
:mod:`~mitsuba_plugins.tracking.equiangular` does) cost 1.5-1.7x the time per sample,
the vertex's code running on every SIMD lane anyway. Exact and unbiased for any grid.
"""
from __future__ import annotations

import functools

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins.guiding.field import cell_index, grid_box, grid_cell, packed
from mitsuba_plugins.tracking import equiangular

#: cells per axis of the light grid
RESOLUTION = 16
#: equal pieces of a segment over which the density is piecewise constant
PIECES = 8
#: floor of a piece's value, as a share of the segment's largest
DEFENSIVE = 0.05
#: the guided density covers at most this optical depth from the segment's start
MAX_OPTICAL_DEPTH = 30.0
#: a cell's value is used once this many vertices fell in it
MIN_RECORDS = 16
#: the value of a cell with fewer records: on a segment, the largest known value there
#: (a cell not yet learnt is not taken for a dark one: with unknown cells at the floor,
#: points went only where records had been, and the tuning set's gap room at max_depth 2
#: had 3.2x the variance of free-flight vertices; 0.61x with this)
UNKNOWN = -1.0
#: share of the guided density drawn toward small lights inside a medium (equiangular,
#: one component per light of :func:`lamps`, equal shares)
LAMP_SHARE = 0.5
#: ... and lights outside the media below this share, where the phase-weighted components
#: are traced (:class:`PhaseLampSegment`: an anisotropic phase function)
SMALL_OUTSIDE_LAMP = 0.5
#: at most this many such lights (more: none; the density's cost grows with each)
MAX_LAMPS = 4
#: equal pieces in angle of :class:`PhaseLampSegment`'s density, and the floor of a
#: piece's weight as a share of the largest
LAMP_PIECES = 4
LAMP_FLOOR = 1e-3
#: a shape emitter counts as small when its bounds' largest side is below this share of
#: the guided box's smallest side
SMALL_LAMP = 0.1
#: guided distances are traced only where some homogeneous medium's optical depth across
#: one cell of the grid is below this: in denser media a segment ends inside one cell,
#: where the learnt values cannot shape its density (the tuning set's dense ball, optical
#: depth 2.5 per cell, lost 1.77x -> 1.38x against volpath with them)
MAX_CELL_DEPTH = 1.0


def traced(guide, media) -> bool:
    """Whether a render traces guided distance sampling: a guided pass asking for it, in a
    scene with a homogeneous medium, none of them chromatic (their flights are weighted
    over channels, docs/method.md section 7)."""
    return (guide is not None and guide.sampling and guide.light is not None
            and media.homogeneous and not media.chromatic_homogeneous)


def cell_size(bbox, resolution: int = RESOLUTION) -> float:
    """The mean side of a cell of an ``resolution^3`` grid over ``bbox`` (host side)."""
    return float(np.mean(np.array(bbox.max) - np.array(bbox.min))) / resolution


def worthwhile(media: list, bbox, resolution: int = RESOLUTION) -> bool:
    """Whether a light grid over ``bbox`` can shape the segments of one of ``media``: a
    homogeneous medium whose largest extinction times the grid's mean cell size is below
    :data:`MAX_CELL_DEPTH` (host side, once per render)."""
    size = cell_size(bbox, resolution)
    for medium in media:
        if not medium.is_homogeneous():
            continue
        mei = dr.zeros(mi.MediumInteraction3f)
        mei.medium = mi.MediumPtr(medium)
        _, _, sigma_t = medium.get_scattering_coefficients(mei)
        if float(np.max(np.array(sigma_t))) * size < MAX_CELL_DEPTH:
            return True
    return False


def lamps(scene: mi.Scene, bbox, boxes: bool = False, outside: bool = False) -> list:
    """Positions of the small lights that sit inside a medium (host side, once per
    render, no kernel launched): point and spot lights, and emitting shapes smaller than
    :data:`SMALL_LAMP` of ``bbox``, whose centre lies in the bounds of a shape with an
    interior medium (anywhere, where the only medium is the camera's). Near such a light
    the once-scattered light grows as the inverse squared distance, which no grid of the
    media's size resolves; the guided density then also draws toward it (equiangular).
    Bounds, not the shape itself: a lamp in a corner of a ball's bounds only costs samples
    (the estimate is unbiased for any positions). Empty where there are more than
    :data:`MAX_LAMPS`. ``boxes``: instead, the bounds ``(lo, hi)`` of those lamps that
    are shapes (:meth:`LightGrid.on_lamp`). ``outside``: lights outside the media count
    too where they are smaller than :data:`SMALL_OUTSIDE_LAMP` of ``bbox`` (the
    phase-weighted components, :class:`PhaseLampSegment`; never in ``boxes``)."""
    side = float(np.min(np.array(bbox.max) - np.array(bbox.min)))
    media = [s.bbox() for s in scene.shapes()
             if s.interior_medium() is not None and not s.is_emitter()]
    # a medium bounded by no shape (the camera's, reaching everywhere): anywhere
    anywhere = not media and any(s.get_medium() is not None for s in scene.sensors())
    found = []
    for emitter in scene.emitters():
        params, box = mi.traverse(emitter), None
        if "position" in params.keys():                    # point light
            p = np.array(params["position"], np.float64).ravel()
        elif mi.has_flag(emitter.flags(), mi.EmitterFlags.DeltaPosition) and \
                "to_world" in params.keys():                # spot light
            p = np.array(params["to_world"].matrix, np.float64).reshape(-1, 4, 4)[0, :3, 3]
        elif emitter.get_shape() is not None and emitter.get_shape().bbox().valid():
            box = emitter.get_shape().bbox()
            p = np.array(box.center(), np.float64).ravel()
        else:
            continue
        size = 0.0 if box is None else float(np.max(np.array(box.max) - np.array(box.min)))
        inside = anywhere or any(bool(b.contains(mi.ScalarPoint3f(*[float(x) for x in p])))
                                 for b in media)
        if (inside and size < SMALL_LAMP * side) or \
                (outside and not boxes and size < SMALL_OUTSIDE_LAMP * side):
            found.append(([float(x) for x in p], box if inside else None))
    if len(found) > MAX_LAMPS:
        return []
    if not boxes:
        return [p for p, _ in found]
    # a margin of 1e-3 of the box's size: points on the surface, found by a ray or
    # sampled, may fall a rounding error outside its exact bounds
    return [(np.array(b.min) - 1e-3 * (np.array(b.max) - np.array(b.min)),
             np.array(b.max) + 1e-3 * (np.array(b.max) - np.array(b.min)))
            for _, b in found if b is not None]


def common_hg(media: list):
    """The asymmetry ``g`` shared by every medium's phase function where each is
    Henyey-Greenstein (isotropic: 0), else None (host side, once per render)."""
    gs = set()
    for medium in media:
        phase = medium.phase_function()
        name = phase.class_name()
        if name == "IsotropicPhaseFunction":
            gs.add(0.0)
        elif name == "HGPhaseFunction":
            gs.add(round(float(np.array(mi.traverse(phase)["g"]).ravel()[0]), 6))
        else:
            return None
    return gs.pop() if len(gs) == 1 else None


def learning(guide) -> bool:
    """Whether a pass records what next-event estimation gathers into the light grid."""
    return guide is not None and guide.recording and guide.light is not None


class LightGrid:
    """Per cell of an ``r^3`` grid over ``bbox``: the mean next-event estimate of the
    medium points that fell in it (channels averaged), learnt between passes."""

    def __init__(self, bbox, resolution: int = RESOLUTION, lamps: list = (),
                 lamp_boxes: list = (), phase_g=None):
        # the Henyey-Greenstein asymmetry every medium shares (:func:`common_hg`; None or
        # 0: the lamps' components are plain equiangular); opaque: another g compiles
        # nothing new
        self.phase_g = dr.opaque(mi.Float, phase_g) if phase_g else None
        self.resolution = int(resolution)
        self.cells = self.resolution ** 3
        self.lo, self.inv_size = grid_box(bbox)
        # the largest gray extinction whose segments take guided points and whose points
        # are recorded (:meth:`takes`); opaque: another scene's compiles nothing new
        self.max_sigma = dr.opaque(mi.Float, MAX_CELL_DEPTH / cell_size(bbox, resolution))
        # where the density also draws toward (:func:`lamps`); opaque: a moved light
        # compiles nothing new
        self.lamps = [dr.opaque(mi.Point3f, p) for p in lamps]
        # the bounds of those that are shapes (:meth:`on_lamp`)
        self.lamp_boxes = [tuple(dr.opaque(mi.Point3f, [float(x) for x in c]) for c in b)
                           for b in lamp_boxes]
        self.sums = np.zeros((self.cells, 2), np.float64)     # value, vertices
        self._upload(np.full(self.cells, UNKNOWN))

    def memory(self) -> int:
        return self.cells * (4 + 2 * 4 + 2 * 8)

    def _upload(self, mean: np.ndarray) -> None:
        """``mean``: per cell, the mean estimate, or :data:`UNKNOWN`."""
        self.mean = mi.Float(mean.astype(np.float32))
        # per cell: the sum of the values and the count, next to each other (one packet
        # scatter per record, field.ACC_STRIDE)
        self.acc = dr.zeros(mi.Float, 2 * self.cells)
        dr.eval(self.mean, self.acc)

    def update(self) -> int:
        """Fold the last pass's records in; returns the cells with a value."""
        self.sums += np.array(self.acc, np.float64).reshape(self.cells, 2)
        value, n = self.sums[:, 0], self.sums[:, 1]
        known = (n >= MIN_RECORDS) & np.isfinite(value)
        self._upload(np.where(known, value / np.where(n > 0, n, 1.0), UNKNOWN))
        return int((known & (value > 0)).sum())

    def cell(self, p: mi.Point3f) -> mi.UInt32:
        return grid_cell(self.lo, self.inv_size, self.resolution, p)

    def takes(self, homogeneous: mi.Bool, sigma_t) -> mi.Bool:
        """The lanes whose medium the grid can shape: all but homogeneous media whose
        extinction (``sigma_t``, read where ``homogeneous``) across one cell exceeds
        :data:`MAX_CELL_DEPTH`. Those media's segments end inside one cell, and their
        points must not be recorded either: a cell that also holds a thin medium (a
        dense cube beside a near-empty one, which one cell of the grid over both
        straddles) would learn the dense medium's dark interior for both (measured on
        the dense family's tuning22_cube_pair_inside: 1.66x the variance of guiding
        without guided distances, whose points the dense cube's records had steered)."""
        return ~homogeneous | (mi.Spectrum(sigma_t)[0] < self.max_sigma)

    def values_along(self, ray: mi.Ray3f, h: mi.Float, n: int, active=True) -> list:
        """The values of the cells holding ``ray((k + 0.5) h)``, ``k = 0 .. n - 1`` (grid
        coordinates stepped along the ray; clamped to the grid)."""
        r = self.resolution
        scale = mi.Vector3f(*self.inv_size) * r
        x = (ray(0.5 * h) - mi.Point3f(*self.lo)) * scale
        step = ray.d * h * scale
        return [dr.gather(mi.Float, self.mean, cell_index(dr.fma(step, k, x), r), active)
                for k in range(n)]

    def on_lamp(self, y: mi.Point3f) -> mi.Bool:
        """Whether the point ``y`` of an emitter lies in the bounds of a lamp that is a
        shape. There next-event estimation at a guided point takes the whole
        contribution (MIS weight 1) and emission found from a vertex whose emitter
        sample that point took counts 0 (``volume_loop``): the guided density draws
        toward the lamp, so its points near the lamp are frequent and their weights
        bounded, while a phase-sampled hit from a free-flight vertex near it is a rare,
        large sample. Any MIS weights that are one function of the vertex, direction
        and light point for both techniques and sum to 1 keep the estimate unbiased."""
        out = mi.Bool(False)
        for lo, hi in self.lamp_boxes:
            out |= dr.all((y >= lo) & (y <= hi))
        return out

    def record(self, p: mi.Point3f, contribution: mi.Spectrum, active) -> None:
        """One medium point's emitter sample per unit of throughput (0 counts)."""
        value = mi.Float(dr.mean(mi.Spectrum(contribution)))
        ok = active & dr.isfinite(value) & (value >= 0)
        cell = self.cell(p)
        dr.scatter_reduce(dr.ReduceOp.Add, self.acc, packed(value, 1.0, stride=2), cell, ok)


def pick_piece(masses: list, target: mi.Float) -> tuple:
    """The piece of a piecewise density whose cumulative mass range holds ``target`` (in
    ``[0, sum(masses))``): ``(index as a float, its mass, the mass before it)``."""
    k, mass, before = mi.Float(0.0), masses[0], mi.Float(0.0)
    running = masses[0]
    for j in range(1, len(masses)):
        take = target >= running
        mass = dr.select(take, masses[j], mass)
        before = dr.select(take, running, before)
        k = dr.select(take, float(j), k)
        running = running + masses[j]
    return k, mass, before


class Segment:
    """The guided density over ``[0, t_end]`` of ``ray`` (unit direction) in a medium of
    gray extinction ``sigma``: ``sigma exp(-sigma t) D_k / Z`` on piece ``k``; pieces of
    length ``h``, the last one reaching to ``t_end`` (which may be infinite)."""

    def __init__(self, grid: LightGrid, ray: mi.Ray3f, t_end: mi.Float, sigma: mi.Float,
                 active):
        self.sigma, self.t_end = sigma, t_end
        self.h = dr.minimum(t_end, MAX_OPTICAL_DEPTH / dr.maximum(sigma, 1e-30)) / PIECES
        D = grid.values_along(ray, self.h, PIECES, active)
        top = functools.reduce(dr.maximum, D)
        # nothing learnt along the segment: the exponential truncated to it; cells not yet
        # learnt (UNKNOWN, below 0) as the brightest known one
        self.D = [dr.select(top > 0, dr.select(d < 0, top, dr.maximum(d, DEFENSIVE * top)),
                            1.0) for d in D]
        # exp(-sigma h k) as powers of one exponential (one exp per segment, not PIECES)
        step, decay = dr.exp(-sigma * self.h), [mi.Float(1.0)]
        for _ in range(1, PIECES):
            decay.append(decay[-1] * step)
        decay.append(dr.exp(-sigma * t_end))
        self.mass = [d * (a - b) for d, a, b in zip(self.D, decay[:-1], decay[1:])]
        self.Z = total = sum(self.mass[1:], self.mass[0])
        self.valid = active & (self.h > 0) & (sigma > 0) & (total > 0) & dr.isfinite(total)
        # toward the small lights in a medium: equiangular components, LAMP_SHARE in all
        # (weighted by the phase function toward the lamp where it is forward- or
        # back-scattering: PhaseLampSegment)
        self.lamps = [equiangular.Segment(ray, t_end, p) if grid.phase_g is None
                      else PhaseLampSegment(ray, t_end, p, grid.phase_g) for p in grid.lamps]
        self.share = LAMP_SHARE if self.lamps else 0.0

    def pdf(self, t: mi.Float) -> mi.Float:
        k = dr.clip(mi.Int32(dr.floor(t / self.h)), 0, PIECES - 1)
        D = mi.Float(0.0)
        for j, d in enumerate(self.D):
            D = dr.select(k == j, d, D)
        p = (1.0 - self.share) * self.sigma * dr.exp(-self.sigma * t) * D / self.Z
        for lamp in self.lamps:
            p += self.share / len(self.lamps) * lamp.pdf(t)
        return dr.select(self.valid & (t >= 0) & (t < self.t_end), p, 0.0)

    def sample(self, u: mi.Float) -> mi.Float:
        """One distance: a lamp's equiangular component where ``u`` falls below the
        lamps' share (``u`` rescaled to pick one and draw within it), else the learnt
        density."""
        if not self.lamps:
            return self._sample_learnt(u)
        n = len(self.lamps)
        lamp_u = u / self.share * n
        pick = dr.minimum(mi.UInt32(lamp_u), n - 1)
        t_lamp = mi.Float(0.0)
        for j, lamp in enumerate(self.lamps):
            t_lamp = dr.select(pick == j, lamp.sample(dr.clip(lamp_u - j, 0.0, 1.0)), t_lamp)
        t_lamp = dr.clip(t_lamp, 0.0, self.t_end)
        t_learnt = self._sample_learnt(
            dr.clip((u - self.share) / (1.0 - self.share), 0.0, 1.0))
        return dr.select(u < self.share, t_lamp, t_learnt)

    def _sample_learnt(self, u: mi.Float) -> mi.Float:
        target = u * self.Z
        k, mass, before = pick_piece(self.mass, target)
        a = k * self.h
        last = a >= (PIECES - 1) * self.h
        b = dr.select(last, self.t_end, a + self.h)
        # within the piece: the exponential truncated to [a, b]
        v = dr.clip((target - before) / dr.maximum(mass, 1e-30), 0.0, 1.0)
        span = 1.0 - dr.exp(-self.sigma * (b - a))
        t = a - dr.log(dr.maximum(1.0 - v * span, 1e-30)) / self.sigma
        return dr.clip(t, a, b)


class PhaseLampSegment(equiangular.Segment):
    """The equiangular density toward a lamp at ``p`` times the phase function toward it:
    along the ray, next-event estimation's contribution at ``ray(t)`` goes as the inverse
    squared distance to the lamp (which equiangular sampling follows) times the phase
    function's value between the ray's direction and the lamp's. In equiangular
    coordinates (``t = Delta + D tan(theta)``, ``theta`` in ``[theta_a, theta_b]``) the
    cosine between the incident direction ``-ray.d`` and the lamp's is ``sin(theta)``, so a
    Henyey-Greenstein phase function of asymmetry ``g`` weighs
    ``(1 + g^2 + 2 g sin(theta))^(-3/2)``: 343x between its ends at ``g`` = 0.75, which
    plain equiangular sampling spreads evenly. The density is piecewise constant in
    ``theta`` over :data:`LAMP_PIECES` equal pieces, each weighted by that factor at its
    middle (at least :data:`LAMP_FLOOR` of the largest): exact for what it samples, and
    positive on the whole segment (Georgiev et al. 2013, "Joint importance sampling of
    low-order volumetric scattering", sample this product too).

    Measured (128x128, 8 alternating renders of 64 spp, guided renders, efficiency over
    plain equiangular components): the tuning set's ``forward_lamp`` (HG 0.75) 4 / 8 / 16
    pieces 1.165 / 1.170 / 1.180 in a first version (two sincos per segment, an arctangent
    in ``pdf``; time +5 / +6 / +9%), so 4; with the transmittance to the lamp in the
    weights too, the same variance for 3% more time. This version: ``forward_lamp`` 1.169
    (relMSE 0.82x, time +4%); the test set's camera inside the cloud (HG 0.6) 1.048
    (relMSE 0.91x, time +4.5%); isotropic media (the lamp ball) keep plain equiangular.

    Small lights outside the media join too where this weighting is traced
    (``lamps(outside=True)``, below :data:`SMALL_OUTSIDE_LAMP` of the guided box): along a
    segment aimed near such a light the phase function's value toward it varies as much.
    The tuning set's ``forward_outside`` (HG 0.85) 1.10 (relMSE 0.87x, time +4%); the
    test set's HG 0.9 ball 1.043 (relMSE 0.91x, time +6%). In the isotropic gap room,
    plain equiangular components toward its light outside gave 0.98: so only with an
    anisotropic phase function."""

    def __init__(self, ray: mi.Ray3f, t_end: mi.Float, p: mi.Point3f, g: float):
        super().__init__(ray, t_end, p)     # Delta, D, theta_a, theta_b
        self.width = (self.theta_b - self.theta_a) / LAMP_PIECES
        # sines and cosines of the pieces' ends and middles by rotations from theta_a
        # (whose sine and cosine the geometry gives): one sincos per segment, and the
        # pieces' ends as distances (pdf finds a piece without an arctangent)
        r_a = dr.rsqrt(dr.square(self.delta) + dr.square(self.D))
        s, c = -self.delta * r_a, self.D * r_a
        hs, hc = dr.sincos(0.5 * self.width)
        w, self.ends = [], []
        for k in range(LAMP_PIECES):
            if k:
                self.ends.append(dr.fma(self.D, s / c, self.delta))
            ms, mc = dr.fma(s, hc, c * hs), dr.fma(c, hc, -s * hs)      # the middle
            x = (1.0 + g * g) + (2.0 * g) * ms
            w.append(dr.rsqrt(x) / x)
            s, c = dr.fma(ms, hc, mc * hs), dr.fma(mc, hc, -ms * hs)    # the next end
        top = functools.reduce(dr.maximum, w)
        self.w = [dr.maximum(x, LAMP_FLOOR * top) for x in w]
        self.Z = sum(self.w[1:], self.w[0])

    def sample(self, u: mi.Float) -> mi.Float:
        """A distance: a piece in proportion to its weight, an angle uniform within it."""
        target = u * self.Z
        k, w, before = pick_piece(self.w, target)
        v = dr.clip((target - before) / dr.maximum(w, 1e-30), 0.0, 1.0)
        th = self.theta_a + (k + v) * self.width
        return self.delta + self.D * dr.tan(th)

    def pdf(self, t: mi.Float) -> mi.Float:
        """The density of ``t``: the piece's share over its width in ``theta``, times
        ``d theta / d t = D / (D^2 + (t - Delta)^2)``."""
        w = self.w[0]
        for end, x in zip(self.ends, self.w[1:]):
            w = dr.select(t >= end, x, w)
        pdf = w / (self.Z * self.width) * self.D / (dr.square(self.D) + dr.square(t - self.delta))
        return dr.select(self.width > 0, pdf, 0.0)


class Point:
    """A segment's guided point for next-event estimation (:func:`plan`)."""

    def __init__(self, p, t, factor, always, valid):
        self.p, self.t, self.factor, self.always, self.valid = p, t, factor, always, valid

    def used(self, scattered: mi.Bool) -> mi.Bool:
        """The lanes whose emitter sample is taken at the point: all valid lanes whose
        segment ends where no other emitter sample is taken, else those that collided."""
        return self.valid & (self.always | scattered)


def plan(grid: LightGrid, ray: mi.Ray3f, coefficients, t_end: mi.Float, smooth_end: mi.Bool,
         eligible: mi.Bool, u: mi.Float) -> Point:
    """Draw the guided point of the segment ``[0, t_end]`` on the ``eligible`` lanes
    (homogeneous media of gray extinction). Its emitter sample stands for the segment's
    where the segment ends at no surface that samples emitters (nothing, or a null
    surface): then on every lane, with weight ``sigma_s exp(-sigma t) / p(t)``. Where it
    ends at such a surface (whose own emitter sample takes the iteration's shadow ray),
    on the lanes whose flight collided, divided by the collision's probability ``1 -
    exp(-sigma t_end)``. Either way its expectation is the segment's next-event term.
    ``coefficients``: the medium's ``(sigma_s, sigma_t)``, as the flight read them;
    ``smooth_end``: whether the segment ends at a surface that samples emitters.

    A conditional: packets with no eligible lane skip the density (a dense medium beside
    a thin one, :meth:`LightGrid.takes`: the dense family's cube pairs spent 40% more
    per sample in their guided pass without it)."""
    sigma_s, sigma = mi.Spectrum(coefficients[0]), mi.Spectrum(coefficients[1])[0]

    def drawn(ray, sigma_s, sigma, t_end, smooth_end, eligible, u):
        seg = Segment(grid, ray, t_end, sigma, eligible)
        t = seg.sample(u)
        p_g = seg.pdf(t)
        always = ~smooth_end
        collide = 1.0 - dr.exp(-sigma * t_end)
        valid = seg.valid & (p_g > 0) & (always | (collide > 0))
        factor = sigma_s * dr.exp(-sigma * t) / (p_g * dr.select(always, 1.0, collide))
        return ray(t), t, dr.select(valid, factor, 0.0), always, valid

    def skipped(ray, sigma_s, sigma, t_end, smooth_end, eligible, u):
        return mi.Point3f(0.0), mi.Float(0.0), mi.Spectrum(0.0), ~smooth_end, mi.Bool(False)
    return Point(*dr.if_stmt((ray, sigma_s, sigma, t_end, smooth_end, eligible, u),
                             eligible, drawn, skipped))
