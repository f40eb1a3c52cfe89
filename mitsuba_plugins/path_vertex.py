"""Surface light transport shared by every integrator of the suite.

The phases of a path vertex, as vectorised functions: emitter selection and sampling
(next-event estimation), emission found by BSDF sampling weighted by MIS, and Russian
roulette. ``path_rr`` composes them; the volumetric integrators reuse them rather than
copy them. Each call draws random numbers in the same order as Mitsuba's C++ ``path``
so that a faithful configuration reproduces its images bit for bit.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.mis import MIS

EMITTER_SELECTIONS = ("uniform", "power")
RR_RULES = ("throughput", "fixed")

#: Fraction of the power-proportional emitter pmf that stays uniform. It keeps the
#: estimator unbiased when the Monte Carlo power estimate of an emitter is 0 (a dim or
#: sparsely textured emitter) and bounds the weight of rarely chosen emitters.
POWER_DEFENSIVE_FRACTION = 0.1
#: Rays per emitter used to estimate its emitted power (flux) at render time.
POWER_ESTIMATE_SAMPLES = 4096


def _mean_channel(spec):
    if mi.is_rgb:
        return mi.luminance(spec)
    return dr.mean(spec, axis=0) if dr.depth_v(spec) > 1 else spec


class EmitterSelection:
    """How next-event estimation picks an emitter, with the matching pdfs.

    ``uniform``: Mitsuba's own rule (each emitter with probability proportional to its
    ``sampling_weight``, i.e. 1/N by default), delegated to the scene.
    ``power``: probability proportional to each emitter's emitted power (flux), estimated
    once per render from ``Emitter.sample_ray`` (whose weight has expectation equal to
    the flux), mixed with ``POWER_DEFENSIVE_FRACTION`` of uniform.

    Built inside ``sample()`` for the scene at hand, never cached on the plugin.
    """

    def __init__(self, scene: mi.Scene, rule: str = "uniform"):
        self.scene = scene
        self.rule = rule
        self.count = len(scene.emitters())
        if rule == "power" and self.count > 1:
            self._build_power_table()
        else:
            self.rule = "uniform"

    def _build_power_table(self):
        n, m = self.count, POWER_ESTIMATE_SAMPLES
        idx = dr.arange(mi.UInt32, n * m) // m
        emitter = dr.gather(mi.EmitterPtr, self.scene.emitters_dr(), idx)
        rng = mi.PCG32(size=n * m, initstate=dr.arange(mi.UInt64, n * m))
        u = [rng.next_float32() for _ in range(5)]
        _, weight = emitter.sample_ray(0.0, u[0], mi.Point2f(u[1], u[2]), mi.Point2f(u[3], u[4]))
        flux = _mean_channel(mi.unpolarized_spectrum(weight))
        flux = dr.select(dr.isfinite(flux) & (flux > 0), flux, 0.0)
        power = dr.block_sum(flux, m) / m
        total = dr.sum(power)
        pmf = dr.select(total > 0, (1 - POWER_DEFENSIVE_FRACTION) * power / total
                        + POWER_DEFENSIVE_FRACTION / n, 1.0 / n)
        self.distr = mi.DiscreteDistribution(pmf)
        # Emitter pointers are registry ids: a table indexed by id maps a hit emitter to
        # its selection probability (id 0 = no emitter -> 0).
        ids = dr.reinterpret_array(mi.UInt32, self.scene.emitters_dr())
        table = dr.zeros(mi.Float, dr.max(ids)[0] + 1 if dr.width(ids) else 1)
        dr.scatter(table, self.distr.eval_pmf_normalized(dr.arange(mi.UInt32, self.count)), ids)
        self.pmf_by_id = table
        dr.eval(self.distr, self.pmf_by_id)

    def sample_direction(self, si, u: mi.Point2f, active, test_visibility: bool = True):
        """Emitter-sampled direction: ``(ds, Le / p)``, ``ds.pdf`` in solid angle
        including the selection probability (Scene::sample_emitter_direction). With
        ``test_visibility`` false the caller accounts for occlusion (and transmittance)."""
        if self.rule == "uniform":
            return self.scene.sample_emitter_direction(si, u, test_visibility, active)
        index, u_x, pmf = self.distr.sample_reuse_pmf(u.x, active)
        emitter = dr.gather(mi.EmitterPtr, self.scene.emitters_dr(), index, active)
        ds, weight = emitter.sample_direction(si, mi.Point2f(u_x, u.y), active)
        ds.pdf *= pmf
        weight *= dr.rcp(pmf)
        visible = active
        if test_visibility:
            visible = active & ~self.scene.ray_test(si.spawn_ray_to(ds.p), active)
        return ds, dr.select(visible & (ds.pdf != 0), weight, 0.0)

    def pdf_direction(self, ref, ds, active):
        """Solid-angle pdf with which :meth:`sample_direction` would draw ``ds``."""
        if self.rule == "uniform":
            return self.scene.pdf_emitter_direction(ref, ds, active)
        ids = dr.reinterpret_array(mi.UInt32, ds.emitter)
        pmf = dr.gather(mi.Float, self.pmf_by_id, ids, active)
        return ds.emitter.pdf_direction(ref, ds, active) * pmf


def emission_mis(scene, emitters: EmitterSelection, mis: MIS, si, prev_si,
                 prev_bsdf_pdf, prev_bsdf_delta, frac_l=1.0):
    """Emission at ``si`` reached by BSDF sampling from ``prev_si``, MIS-weighted.

    After a delta lobe (or at the camera, where ``prev_bsdf_delta`` is set) the emitter
    pdf is 0 and the emission counts in full. ``frac_l``: as for
    :func:`emitter_contribution` (the probability that ``prev_si`` sampled an emitter,
    where it did so with one).
    """
    ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
    p_l = emitters.pdf_direction(prev_si, ds, ~prev_bsdf_delta)
    w_b = mis.weight(prev_bsdf_pdf, p_l * frac_l, emitter_technique=False)
    return w_b * ds.emitter.eval(si, prev_bsdf_pdf > 0)


def sample_emitter(emitters: EmitterSelection, si, u: mi.Point2f, active,
                   test_visibility: bool = True):
    """Next-event estimation, first half: ``(ds, Le / p_l, wo local, active)``."""
    ds, em_weight = emitters.sample_direction(si, u, active, test_visibility)
    # Not `active &= ...`: that would shrink the caller's mask in place.
    return ds, em_weight, si.to_local(ds.d), active & (ds.pdf != 0)


def emitter_contribution(mis: MIS, si, ds, em_weight, wo, bsdf_val, p_b,
                         frac_l: float = 1.0, frac_b: float = 1.0):
    """Next-event estimation, second half: ``f * Le / p_l * w_l`` (w_l = 1 for delta lights).

    ``frac_l``, ``frac_b``: sample counts of the two techniques (any common scale), so the
    heuristic sees effective densities n_l p_l and n_b p_b (1 sample each by default).
    """
    bsdf_val = si.to_world_mueller(bsdf_val, -wo, si.wi)
    w_l = dr.select(ds.delta, 1.0, mis.weight(ds.pdf * frac_l, p_b * frac_b, emitter_technique=True))
    return bsdf_val * em_weight * w_l


class RussianRoulette:
    """Path termination (docs/method.md section 5) after ``rr_depth`` path vertices.

    ``throughput`` (Mitsuba's rule): survival s = clamp(max(beta) * eta^2, s_min, s_max),
    s_max = 0.95 in Mitsuba. ``fixed``: survival s = ``survival`` at every vertex.
    On survival beta /= s, so the estimator stays unbiased.
    """

    def __init__(self, rr_depth: int, rule: str = "throughput", survival: float = 0.95,
                 min_survival: float = 0.0, max_survival: float = 0.95):
        self.rr_depth = rr_depth
        self.rule = rule
        self.survival = survival
        self.min_survival = min_survival
        self.max_survival = max_survival

    def survival_probability(self, beta_max, eta):
        if self.rule == "fixed":
            return mi.Float(self.survival)
        s = dr.minimum(beta_max * dr.square(eta), self.max_survival)
        if self.min_survival > 0:
            s = dr.maximum(s, self.min_survival)
        return s

    def apply(self, beta, eta, depth, u, active=True, gain=None):
        """Returns ``(beta, alive)``; ``u`` is drawn by the caller on every lane
        (Mitsuba draws it whether or not roulette is active). Lanes outside
        ``active`` play no roulette. ``gain``: where paths were guided, the ratio of the
        throughput the unguided sampler would have (its own weights ``f / p``) to
        ``beta``. Survival then follows the larger of the two throughputs: a guided
        vertex lowers ``beta`` exactly where it chose a direction the field trusts, and
        survival by ``beta`` alone kills those paths (a firefly when one survives with
        ``1 / s``); survival by the unguided throughput alone lifts paths whose guided
        weights exceeded the unguided ones by ``1 / gain``. With the larger of the two,
        a survivor's ``beta / s`` stays at most 1 in its largest channel, as without
        guiding (docs/method.md section 13)."""
        beta_max = dr.max(mi.unpolarized_spectrum(beta))
        s = self.survival_probability(
            beta_max if gain is None else beta_max * dr.maximum(gain, 1.0), eta)
        rr_active = active & (depth >= self.rr_depth)
        beta[rr_active] *= dr.rcp(s)
        alive = (~rr_active | (u < s)) & (beta_max != 0)
        return beta, alive

    def __repr__(self):
        if self.rule == "fixed":
            return f"fixed (survival {self.survival:g}, from depth {self.rr_depth})"
        return (f"throughput (survival in [{self.min_survival:g}, {self.max_survival:g}], "
                f"from depth {self.rr_depth})")
