"""Guided directions at medium vertices and the records that train the field
(docs/method.md section 13).

:func:`resample`: resampled importance sampling (Talbot, Cline and Egbert 2005) of the
product of the phase function ``f`` and the learnt incident radiance ``g``
(:meth:`GuidingField.pdf`). ``M`` candidates are drawn from the phase function (the
first is the path's own phase sample). Where every phase function of the scene is
symmetric about the incident direction (all but microflake ones), the others are the
first turned about that direction by ``2 pi j / M``: each is still distributed as the
phase function, which is all that resampling needs to stay unbiased (the candidates may
depend on each other), at the cost of a rotation instead of a sample and its random
numbers (measured: the same variance per sample on the tuning scenes; the cloud's final
pass 603 -> 557 ms). Candidate ``j`` weighs ``w_j = g(x_j) f(x_j) /
p(x_j)``; one is chosen in proportion, and the path's weight for the vertex is
``mean(w) / g(y)`` instead of ``f(y) / p(y)``. That estimates ``int f L`` without bias
for any ``g > 0`` (every trained cell keeps a uniform share); where ``g`` follows the
incident radiance the weight times what follows varies little, and where ``g`` is uniform
(untrained cells) the weight is exactly ``f / p``: a mixture of guide and phase function
(one-sample MIS) was tried first and lost, its per-vertex weights ``f / (a g + (1 - a) f)``
multiplying into a heavy tail over the tens of vertices of a dense medium (variance 90x
that of the phase function alone on a dense ball).

Where a cell's lobe is concentrated (:data:`LOBE_KAPPA`), ``guiding_lobe`` more
candidates are drawn from ``g`` itself, and every candidate weighs ``f g / (M_f p + M_g
g)`` (resampling with the balance heuristic over its candidates' densities; Talbot et
al.'s multiple-importance form): phase samples alone seldom reach light that comes from
outside the phase function's cone, and a lobe's samples bound the weights where ``f``
is small and ``g`` large. This is still not the one-sample mixture above: the vertex's
weight is ``sum(w) / g(y)``, not a ratio of two densities at one sample.

The MIS weights of next-event estimation and of emission found by the scattered ray keep
the phase function's pdf: any weights that sum to one over the two techniques leave the
sum unbiased, and resampling estimates the emission term's weighted integrand as well as
any other.

:class:`Records`: a reservoir of ``SLOTS`` medium vertices of each path, in the loop
state (every vertex kept with probability ``SLOTS / n``, ``n`` the path's medium
vertices). A slot holds the vertex's cell and sampled direction, the radiance ``L`` gathered so far and ``1 / (beta f(y))``. When the path ends, it adds
``n / SLOTS x mean_c((L_end - L_then) / (beta_c f(y)))`` to its cell's sums: all the path gathered
after the vertex along ``y``, over ``y``'s density (exact in unguided passes,
``f(y) g(y) / mean(w)`` approximately in guided ones): an estimate of the integral of
incident radiance. A ring of the last vertices was tried first: it kept what the next
few vertices gathered only, which in a dense medium points every cell toward the lit side
(variance 3.2x that of the phase function at depth 64 on a dense ball).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

VARIANT = mi.variant()

#: medium vertices a path keeps records of at once (the ring's size)
SLOTS = 4


def turned(axis: mi.Vector3f, d: mi.Vector3f, n: int) -> list:
    """``d`` turned about ``axis`` by ``2 pi j / n``, ``j = 1 .. n - 1``, as unit vectors.

    Both are normalised here: ``along`` is quadratic in the axis, so an axis of length
    ``1 + e`` gives turned directions of length about ``1 + 2e``. The next vertex's
    incident direction is this one's turned sample, so the error doubled at every guided
    vertex of a walk. Measured before the fix (the camera inside the cloud, 8 renders of
    128x128 at 64 spp): 0.15% of guided vertices had directions off unit length by more
    than 1e-3 and 1 in 70000 by more than 0.5. Such a ray's distances are in the wrong
    units, and 20 samples came out NaN or Inf (zeroed and counted by the sample guard)."""
    axis = dr.normalize(axis)
    along = axis * dr.dot(axis, d)
    across, side = d - along, dr.cross(axis, d)
    out = []
    for j in range(1, n):
        c, s = math.cos(2 * math.pi * j / n), math.sin(2 * math.pi * j / n)
        out.append(dr.normalize(along + across * c + side * s))
    return out


#: resampling draws candidates from a cell's lobe (``guiding_lobe``) only where its
#: concentration ``kappa`` is above this (mean cosine about 0.3). Tuning set, 128x128, 6
#: renders of 64 spp, one lobe candidate, efficiency over phase candidates alone at
#: kappa 0 (before the conditional below) / 1 / 2: ``forward_lamp`` 1.19 / 1.34 / 1.30,
#: lamp ball 1.11 / 1.10 / 1.05, dense ball 0.90 / 0.98 / 0.99, gap room 0.96 / 0.98 / -
#: (flat lobes' samples are near-uniform directions that add noise to the weights' sum,
#: and their cost)
LOBE_KAPPA = 1.0
#: ... and only at a path's first this many real vertices (``depth``): where its
#: throughput is largest; later vertices paid the draws' time for little (tuning set,
#: 128x128, 8 renders of 64 spp, efficiency over no lobe candidates, every vertex / the
#: first 3 / the first 2: ``forward_lamp`` 1.30 / 1.35 / 1.18, lamp ball 1.04 / 1.08 / -,
#: dense ball 0.98 / 0.99 / 0.99, gap room 0.98 / 0.98 / -)
LOBE_DEPTH = 3


def resample(field, phase, phase_ctx, mei, sampler, candidates: int, first, active,
             symmetric: bool = False, lobe: int = 0, depth=None):
    """The guided direction at a medium vertex: ``(y, weight, phase pdf of y, f(y),
    gain)``, ``gain`` the phase function's own weight ``f(y) / p(y)`` over ``weight``
    (1 where not guided: the roulette's ``gain``).
    ``first``: the path's own phase sample ``(wo, weight, pdf)``; the other
    ``candidates - 1`` are ``first`` turned about ``mei.wi`` where ``symmetric`` (every
    phase function of the scene is symmetric about it), else drawn here (``next_1d``,
    ``next_2d`` each); then ``lobe`` candidates are drawn from the cell's learnt
    distribution ``g`` (``next_2d`` each) where the cell's lobe is concentrated
    (:data:`LOBE_KAPPA`) and ``depth`` (the path's real vertices so far; None: any) is
    below :data:`LOBE_DEPTH`, and ``next_1d`` chooses.

    With ``M_f = candidates`` phase samples and ``M_g = lobe`` samples of ``g``, candidate
    ``x`` weighs ``f(x) g(x) / (M_f p(x) + M_g g(x))`` (resampling with the balance
    heuristic over its candidates' densities: each candidate needs only its own
    marginal density, so the turned ones may depend on the first), and the path's
    weight is ``sum(w) / g(y)``. Without ``lobe`` that is the phase-only form above."""
    cell = field.cell(mei.p)
    density = field.lookup(cell, active)
    if symmetric:
        samples = [first] + [(wo, first[1], first[2])
                             for wo in turned(mei.wi, first[0], candidates)]
    else:
        us = [(sampler.next_1d(active), sampler.next_2d(active)) for _ in range(candidates - 1)]
        samples = [first] + [phase.sample(phase_ctx, mei, u1, u2, active) for u1, u2 in us]
    # per candidate: direction, f / p (channels averaged), the phase function's pdf p, g
    cands = [(wo, mi.Float(dr.mean(mi.Spectrum(w))), p, density(wo)) for wo, w, p in samples]
    if lobe:
        # only where the cell's lobe is concentrated (LOBE_KAPPA): elsewhere its samples
        # are near-uniform directions that add noise to the weights' sum (a deterministic
        # choice per vertex, so the weights stay unbiased)
        sharp = active & (field.lobe(cell, active)[1] > LOBE_KAPPA)
        if depth is not None:
            sharp &= depth < LOBE_DEPTH
        m_g = dr.select(sharp, float(lobe), 0.0)

        def drawn(u, sharp):
            wo = field.sample(cell, u, sharp)
            f, p = phase.eval_pdf(phase_ctx, mei, wo, sharp)
            f = mi.Float(dr.mean(mi.Spectrum(f)))
            return wo, dr.select(sharp & (p > 0), f / p, 0.0), p, density(wo)

        def skipped(u, sharp):
            return mi.Vector3f(0, 0, 1), mi.Float(0.0), mi.Float(0.0), mi.Float(0.0)
        # a conditional: packets with no such lane skip the sample and the phase call
        # (the dense ball's 4-spp-trained cells are mostly flat: +2.7% time against +7%)
        cands += [dr.if_stmt((sampler.next_2d(active), sharp), sharp, drawn, skipped)
                  for _ in range(lobe)]
        weights = [r * p * g / dr.maximum(candidates * p + m_g * g, 1e-30)
                   for _, r, p, g in cands]
    else:     # the phase-only form, as it was
        weights = [r * g / candidates for _, r, p, g in cands]
    total = weights[0]
    for w in weights[1:]:
        total = total + w
    target = sampler.next_1d(active) * total
    (y, ratio, pdf, g), running = cands[0], weights[0]
    for (wo, r, p, gj), w in zip(cands[1:], weights[1:]):
        take = target >= running
        y, pdf = dr.select(take, wo, y), dr.select(take, p, pdf)
        ratio, g = dr.select(take, r, ratio), dr.select(take, gj, g)
        running = running + w
    weight = dr.select(g > 0, total / g, 0.0)
    # the unguided weight of y over the guided one (roulette's gain)
    gain = dr.select(active & (weight > 0), ratio / weight, 1.0)
    # lanes not guided keep the phase function's own sample
    wo0, weight0, pdf0 = first
    return (dr.select(active, y, wo0), dr.select(active, mi.Spectrum(weight), weight0),
            dr.select(active, pdf, pdf0), dr.select(active, ratio, cands[0][1]) *
            dr.select(active, pdf, pdf0), gain)


#: a path stops being guided once its guided weights have grown this many times over the
#: unguided ones (its ``gain`` below ``1 / MAX_GROWTH``): resampling weights multiply over
#: a walk, and under a field learnt from few records a walk of tens of vertices could
#: gather a weight of thousands (measured: one sample of 1300 in a dense ball's 4-spp
#: training pass, where its pixel's mean is 0.04). Whether to guide a vertex may depend on
#: the path so far without bias: each vertex's estimate stays unbiased given the past.
MAX_GROWTH = 4.0


def still_guided(gain: mi.Float) -> mi.Bool:
    """The lanes whose next vertex may still be guided (:data:`MAX_GROWTH`)."""
    return gain * MAX_GROWTH >= 1.0

#: the lowest survival probability of :func:`roulette` (its threshold is volpath_delta's
#: ``guiding_roulette``, default ``guided_render.ROULETTE``)
MIN_SURVIVAL = 0.05


def roulette(field, threshold: float, ref: mi.Float, p: mi.Point3f, beta: mi.Spectrum,
             u: mi.Float, active: mi.Bool, gain=None):
    """Roulette by the learnt radiance (the killing half of Vorba and Krivanek 2016's
    adjoint-driven roulette and splitting): at a medium vertex of learnt fluence ``phi``,
    the path's score ``mean(beta) phi`` is compared with ``ref``, its score at its first
    such vertex (an estimate of what the pixel expects of it); where the share ``s`` is
    below ``threshold`` the path survives with ``max(s / threshold, MIN_SURVIVAL)`` and its
    throughput is divided by that: unbiased for any field, since survival is never 0.
    ``gain`` (as for ``RussianRoulette.apply``): the score takes the larger of ``beta``
    and the unguided throughput, so that a path which guided directions sent toward the
    light is not killed for the low weights they gave it. Returns ``(ref, beta, alive)``."""
    phi = field.radiance(field.cell(p), active)
    score = mi.Float(dr.mean(mi.Spectrum(beta))) * phi
    if gain is not None:
        score *= dr.maximum(gain, 1.0)
    known = active & (phi > 0)
    first = known & (ref <= 0)
    ref = dr.select(first, score, ref)
    play = known & ~first & (score < threshold * ref)
    q = dr.clip(score / (threshold * ref), MIN_SURVIVAL, 1.0)
    beta = dr.select(play, beta * dr.rcp(q), beta)
    return ref, beta, ~play | (u < q)


def _fields():
    out = {"next": mi.UInt32, "first_cell": mi.UInt32, "first_L": mi.Float}
    for k in range(SLOTS):
        out.update({f"cell{k}": mi.UInt32, f"d{k}": mi.Vector3f, f"valid{k}": mi.Bool,
                    f"L{k}": mi.Spectrum, f"w{k}": mi.Spectrum})
    return out


class Records:
    """The ring of the last :data:`SLOTS` medium vertices of each path, and where its
    first vertex lay and what it had gathered there (:meth:`GuidingField.record_flow`)."""
    DRJIT_STRUCT = _fields()

    def __init__(self):
        self.next = mi.UInt32(0)
        self.first_cell, self.first_L = mi.UInt32(0), mi.Float(0.0)
        for k in range(SLOTS):
            setattr(self, f"cell{k}", mi.UInt32(0))
            setattr(self, f"d{k}", mi.Vector3f(0.0))
            setattr(self, f"valid{k}", mi.Bool(False))
            setattr(self, f"L{k}", mi.Spectrum(0.0))
            setattr(self, f"w{k}", mi.Spectrum(0.0))

    @staticmethod
    def _value(L, L_then, w):
        """The mean over channels of what was gathered since, per unit of the record's
        weight (channels whose throughput was 0 count 0: a bias of the field only)."""
        return dr.mean((L - L_then) * w)

    def add(self, field, p: mi.Point3f, wo: mi.Vector3f, L: mi.Spectrum, beta: mi.Spectrum,
            f_wo: mi.Float, u: mi.Float, active: mi.Bool, L_pre: mi.Spectrum) -> "Records":
        """The ``active`` medium vertices (before their throughput takes the sampled
        direction's weight) enter the reservoir: the ``n``-th vertex of a path replaces
        slot ``floor(u n)`` where that is below :data:`SLOTS` (reservoir sampling: every
        vertex of the path ends up in it with probability ``SLOTS / n``). ``L_pre``: the
        path's light before this vertex's emitter sample; at a path's second vertex, what
        its first vertex's emitter sample and sampled direction found directly."""
        cell = field.cell(p)
        w = mi.Spectrum(dr.select(beta * f_wo > 0, dr.rcp(beta * f_wo), 0.0))
        self.first_cell[active & (self.next == 0)] = cell
        self.first_L[active & (self.next == 1)] = dr.mean(L_pre)
        self.next[active] += 1
        slot = dr.select(self.next <= SLOTS, self.next - 1,
                         mi.UInt32(dr.floor(u * mi.Float(self.next))))
        for k in range(SLOTS):
            here = active & (slot == k)
            getattr(self, f"cell{k}")[here] = cell
            getattr(self, f"d{k}")[here] = wo
            getattr(self, f"valid{k}")[here] = True
            getattr(self, f"L{k}")[here] = L
            getattr(self, f"w{k}")[here] = w
            self._keep(k, here, p)
        return self

    def _keep(self, k: int, here: mi.Bool, p: mi.Point3f) -> None:
        """What a subclass keeps more of a vertex in slot ``k``."""

    def _flushed(self, field, k: int, value: mi.Float, valid: mi.Bool) -> None:
        """What a subclass records more of slot ``k`` (its ``value``, :meth:`flush`)."""

    def flush(self, field, L: mi.Spectrum, active, weight=1.0) -> None:
        """At the end of the paths: every slot adds what came after its vertex, times
        ``n / SLOTS`` where the path had ``n > SLOTS`` vertices (the inverse of the
        probability that the reservoir kept it). Each path with a vertex adds the light
        it gathered beyond its first vertex's direct light (from its second vertex on),
        all its light, and its square times ``weight`` (its pixel's, as for
        :meth:`GuidingField.record_nee`) to :meth:`GuidingField.record_flow`."""
        total = mi.Float(dr.mean(L))
        direct = dr.select(self.next >= 2, self.first_L, total)
        field.record_flow(self.first_cell, total - direct, total, active & (self.next > 0),
                          weight)
        scale = dr.maximum(mi.Float(self.next) / SLOTS, 1.0)
        for k in range(SLOTS):
            value = scale * self._value(L, getattr(self, f"L{k}"), getattr(self, f"w{k}"))
            valid = active & getattr(self, f"valid{k}")
            field.record(getattr(self, f"cell{k}"), getattr(self, f"d{k}"), value, valid,
                         scale)
            self._flushed(field, k, value, valid)
        self._done(field)

    def _done(self, field) -> None:
        """What a subclass does once every slot is flushed."""


def _surface_fields():
    out = _fields()
    out.update({f"p{k}": mi.Point3f for k in range(SLOTS)})
    out.update({f"t{k}": mi.Float for k in range(SLOTS)})
    out["last"] = mi.UInt32
    return out


class SurfaceRecords(Records):
    """:class:`Records` of surface vertices that also keep each vertex's position and the
    distance its sampled ray went to the next vertex (:meth:`hit`), for the field's
    portals: each path hands the slot that brought it the most light to
    :meth:`HistogramField.record_portal`."""
    DRJIT_STRUCT = _surface_fields()

    def __init__(self):
        super().__init__()
        for k in range(SLOTS):
            setattr(self, f"p{k}", mi.Point3f(0.0))
            setattr(self, f"t{k}", mi.Float(dr.inf))
        self.last = mi.UInt32(SLOTS)

    def hit(self, t: mi.Float, active) -> None:
        """The path's ray since its last vertex went ``t`` (inf: it left the scene): that
        vertex's slot, if it kept one, learns it."""
        for k in range(SLOTS):
            getattr(self, f"t{k}")[active & (self.last == k)] = t
        self.last[active] = SLOTS

    def _keep(self, k, here, p):
        getattr(self, f"p{k}")[here] = p
        getattr(self, f"t{k}")[here] = dr.inf
        self.last[here] = k

    def _flushed(self, field, k, value, valid):
        # the slot that brought the most light (one record per path: one scatter)
        v = dr.select(valid & dr.isfinite(value), value, 0.0)
        if k == 0:
            self._best, self._best_value = mi.UInt32(0), v
        else:
            better = v > self._best_value
            self._best = dr.select(better, k, self._best)
            self._best_value = dr.select(better, v, self._best_value)

    def _done(self, field):
        def pick(name):
            out = getattr(self, f"{name}0")
            for k in range(1, SLOTS):
                out = dr.select(self._best == k, getattr(self, f"{name}{k}"), out)
            return out
        lane = dr.arange(mi.UInt32, dr.width(self._best_value))
        field.record_portal(lane, pick("cell"), pick("p"), pick("d"), pick("t"),
                            self._best_value, self._best_value > 0)


def mix_surface(field, fraction: float, bsdf, bsdf_ctx, si, d_light, p_light, bs, weight,
                u_select, u_dir, active, active_light=True, portal: float = 0.0):
    """The guided choice at a surface whose BSDF has no delta or transmissive lobe: with
    probability ``fraction`` (where the cell has a lobe) a direction from the field, else
    the BSDF's own sample ``bs``; one-sample MIS, pdf ``(1 - a) p_bsdf + a g``. Surface
    paths are short, so the mixture's weights (at most ``1 / (1 - a)`` times the BSDF's)
    do not compound as they do over a walk in a medium. Returns ``(pdf of d_light, the
    sample, its weight, gain, the sample's MIS pdf)`` (``gain``: the BSDF's own weight
    of the sample over the mixture's, ``pdf / p_bsdf``, for the roulette): the mixture
    pdf of the emitter sample's direction is the BSDF side of next-event estimation's
    MIS, and the sample's MIS pdf that of emission found by the new ray;
    ``active_light``: the lanes that sampled an emitter (elsewhere that pdf is not
    needed, and its two lookups are skipped). ``portal`` (``path_rr``'s
    ``guiding_portal``): where the cell has a learnt portal, first with this probability
    the direction toward a point uniform on it (:meth:`HistogramField.portal_sample`),
    and the sample's pdf ``b p_portal + (1 - b) ((1 - a) p_bsdf + a g)``. The MIS
    weights between emitter samples and this choice leave the portal's term out on both
    sides (``(1 - a) p_bsdf + a g`` for the emitter sample's direction and for the
    emission a sampled direction finds): they still sum to 1 for every direction, so the
    estimate stays unbiased, and the portal's density is evaluated once per vertex,
    not twice."""
    cell = field.cell(si.p)
    alpha = dr.select(active & field.trained(cell, active), fraction, 0.0)
    guided = alpha > 0
    opening = portal > 0 and getattr(field, "has_portals", False)
    if opening:
        # first, with probability ``portal``, toward a point of the cell's learnt portal
        # (HistogramField.portals); the rest of u_select chooses as below
        centre, half, inv_area = field.portal(cell, guided)
        beta = dr.select(guided & (inv_area > 0), portal, 0.0)
        use_portal = u_select < beta
        u_select = dr.select(use_portal, u_select, (u_select - beta) / (1.0 - beta))
        aimed = field.portal_sample(centre, half, u_dir) - si.p
        use_portal &= dr.squared_norm(aimed) > 1e-12       # (a point at the vertex: a null set)
    use = guided & (u_select < alpha)
    if opening:
        use &= ~use_portal
    side = dr.select(si.wi.z < 0, -1.0, 1.0)

    def folded(local, active=guided):
        """The lobe folded onto the side of ``wi`` (a direction below the surface is
        mirrored above it): density g(w) + g(mirror(w)) there, 0 on the other side."""
        mirrored = mi.Vector3f(local.x, local.y, -local.z)
        g = field.pdf(cell, si.to_world(local), active) + \
            field.pdf(cell, si.to_world(mirrored), active)
        return dr.select(local.z * side > 0, g, 0.0)
    drawn = si.to_local(field.sample(cell, u_dir, use))
    drawn.z = dr.select(drawn.z * side < 0, -drawn.z, drawn.z)
    wo = dr.select(use, drawn, bs.wo)
    if opening:
        wo = dr.select(use_portal, si.to_local(dr.normalize(aimed)), wo)
        use |= use_portal
    f, p_bsdf = bsdf.eval_pdf(bsdf_ctx, si, wo, guided)
    pdf = mis_pdf = dr.lerp(p_bsdf, folded(wo), alpha)
    if opening:
        pdf = dr.lerp(pdf, field.portal_pdf(centre, half, inv_area, si.p, si.to_world(wo)), beta)
    sample = mi.BSDFSample3f(bs)
    sample.wo = wo
    sample.pdf = dr.select(guided, pdf, bs.pdf)
    sample.eta = dr.select(use, 1.0, bs.eta)
    sample.sampled_type = dr.select(use, mi.UInt32(+mi.BSDFFlags.DiffuseReflection),
                                    bs.sampled_type)
    mixed_weight = dr.select(guided, dr.select(pdf > 0, f / pdf, 0.0), weight)
    gain = dr.select(guided & (p_bsdf > 0), pdf / dr.maximum(p_bsdf, 1e-30), 1.0)
    p_light = dr.select(guided, dr.lerp(
        p_light, folded(si.to_local(d_light), guided & active_light), alpha), p_light)
    return p_light, sample, mi.Spectrum(mixed_weight), gain, \
        dr.select(guided, mis_pdf, bs.pdf)
