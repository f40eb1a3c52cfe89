r"""Gradients of ``volpath_delta`` by path replay (docs/method.md section 11).

Mitsuba's ``RBIntegrator`` scaffolding (``render_forward`` / ``render_backward``) runs a
sample function twice with the same random numbers: a primal pass that returns each
sample's radiance ``L``, then a *replay* that walks the same path again and, at every
event whose weight depends on a scene parameter, propagates the derivative of that
weight times the radiance the path gathered *after* the event (Vicini, Speierer and
Jakob 2021). Nothing is stored per vertex: memory does not grow with path length.

The replay traces exactly the primal path loop (:func:`mitsuba_plugins.volume_loop.trace_volumes`)
with a :class:`Replay` handed to it; every sampling decision stays detached, and the
hooks re-evaluate the parameters they need under ``dr.resume_grad``:

* **segments** (free flights and shadow rays): the derivative of a transmittance is
  :math:`-\int \partial\sigma_t\,ds` times what follows. It is estimated from one
  point uniform over each piece of a shadow ray and one per step on free flights, with
  hashed numbers (:meth:`Replay.uniform`: the path's sampler is never touched):
  differential
  tracking after Nimier-David, Mueller, Keller and Jakob 2022, with no division by the
  null density (``gradient_estimator = "drt"``);
* ``"delta"``: differentiate the delta-tracking estimator itself, as ``prbvolpath``
  does: a null collision weighs :math:`\sigma_n(\theta) / \sigma_n` (variance grows
  as :math:`1 / \sigma_n` where the majorant is tight);
* **real scattering**: :math:`\sigma_s(\theta) / \sigma_s` (density, ``scale``,
  ``albedo``) and the phase function's value over its detached value (``g``);
* **surfaces**: the BSDF's value over its detached value (as ``prb``);
* **light gathered** (medium emission, emitter samples): the attached term itself.

Emitters' own parameters, shapes and visibility are not differentiated (see
docs/usage.md "Gradients").
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.tracking.shadow_rays import shadow_pieces
from mitsuba_plugins.tracking.trackers import medium_interaction

VARIANT = mi.variant()


#: Propagation flags of every term. Terms share parts of the graph (one lookup gives
#: ``sigma_s`` and ``sigma_n``; every lookup shares the grid's tensor and ``scale``),
#: so edges are kept (Dr.Jit's default deletes them after the first traversal, and the
#: second term would see no parameter); interior gradients are cleared so that none is
#: propagated twice. A term may not depend on the parameters being differentiated (the
#: phase function's value when only the density is).
AD_FLAGS = dr.ADFlag.ClearInterior | dr.ADFlag.ClearInput | dr.ADFlag.AllowNoGrad

#: Salt of the replay's hashed random numbers (never the path's sampler).
HASH_SALT = 0x9E3779B9


def lane_keys(lane: mi.UInt32, seed, salt: int) -> mi.UInt32:
    """A hashed key per lane for a render's ``seed``, apart for each ``salt``."""
    # opaque: a literal seed would make every render with a new seed a new kernel
    seed = dr.opaque(mi.UInt32, seed) if isinstance(seed, int) else mi.UInt32(seed)
    return mi.sample_tea_32(lane, seed + salt)[0]


def _bits(x: mi.Float) -> mi.UInt32:
    return dr.reinterpret_array(mi.UInt32, mi.Float(x))


class Replay:
    """What the replay of one path needs besides the loop state: the mode
    (``dr.ADMode.Backward`` or ``Forward``), the adjoint radiance ``dL`` of each sample
    (backward), the primal radiance ``L_primal`` (what the whole path gathers), a
    per-lane ``key`` for hashed random numbers and the segment rule (``estimator``:
    :data:`GRADIENT_ESTIMATORS`).

    Hooks return the forward-mode tangent they add (0 in backward mode, where they
    accumulate into the parameters' gradients by ``dr.backward_from``)."""

    def __init__(self, mode, dL, L_primal, seed, estimator: str):
        self.mode, self.dL, self.L_primal, self.estimator = mode, dL, L_primal, estimator
        #: the free flights' rule (:data:`GRADIENT_ESTIMATORS`)
        self.flight = GRADIENT_ESTIMATORS[estimator]()
        self.key = lane_keys(dr.arange(mi.UInt32, dr.width(L_primal)), seed, HASH_SALT)

    def ray_key(self, ray: mi.Ray3f, salt: int = 0) -> mi.UInt32:
        """A key for numbers along ``ray`` (its origin and direction hashed in)."""
        h = _bits(ray.o.x) ^ (_bits(ray.o.y) * 0x85EBCA6B) ^ (_bits(ray.o.z) * 0xC2B2AE35)
        h ^= _bits(ray.d.x) * 0x27D4EB2F + _bits(ray.d.y) + salt
        return mi.sample_tea_32(self.key, h)[0]

    def uniform(self, ray: mi.Ray3f, t: mi.Float) -> mi.Float:
        """A uniform number for position ``t`` of ``ray``, with no state."""
        return mi.sample_tea_float32(self.ray_key(ray), _bits(t), 6)

    def at_depth(self, depth: mi.UInt32) -> None:
        """Set ``matching``: the lanes whose next flight ``sm`` matches (the first, at
        depth 0; a call, not an assignment, so that the loop takes it for no state)."""
        self.matching = depth == 0

    @property
    def forward(self) -> bool:
        return self.mode == dr.ADMode.Forward

    def emit(self, term: mi.Spectrum, active) -> mi.Spectrum:
        """Propagate the attached ``term`` (a part of the sample's radiance whose value
        is detached elsewhere) on ``active`` lanes; returns its tangent (forward)."""
        with dr.resume_grad():
            term = dr.select(active, term, 0.0)
            if self.forward:
                return mi.Spectrum(dr.select(active, dr.forward_to(term, flags=AD_FLAGS), 0.0))
            dr.backward_from(self.dL * term, flags=AD_FLAGS)
        return mi.Spectrum(0.0)

    def factor(self, weight: mi.Spectrum, after: mi.Spectrum, active) -> mi.Spectrum:
        """A factor of the path's weight, ``weight`` attached, that multiplies the
        radiance ``after`` (detached) gathered after it: propagates ``after * dweight /
        weight``. Lanes whose factor is 0 gather nothing after it and take no part."""
        with dr.resume_grad():
            value = dr.detach(weight)
            ratio = dr.select(value != 0, weight / dr.select(value != 0, value, 1.0), 0.0)
            return self.emit(after * ratio, active)

    def transmittance(self, tau: mi.Spectrum, after: mi.Spectrum, active) -> mi.Spectrum:
        """A transmittance factor ``exp(-tau)`` (``tau`` an attached, unbiased estimate
        of the optical depth of a stretch) in front of ``after``: propagates
        ``-after * dtau``."""
        with dr.resume_grad():
            return self.emit(-after * (tau - dr.detach(tau)), active)


def attached(fn):
    """``fn()`` with gradients resumed (the replay runs under ``dr.suspend_grad``)."""
    with dr.resume_grad():
        return fn()


# -- the shadow rays' transmittance, estimated once per gradient render ----------------
class ShadowNumbers:
    """The random numbers of one vertex's shadow ray in a gradient render: a PCG32
    stream seeded from the lane and the vertex (:meth:`ShadowStore.numbers`), not the
    path's sampler, so that the replay may skip a shadow ray's walk (its estimate kept
    from the primal pass) and still draw the path's numbers in step. Passed where a
    sampler is (``next_1d``); a loop carries it as its state."""
    DRJIT_STRUCT = {"rng": mi.PCG32}

    def __init__(self, rng=None):
        self.rng = rng

    def next_1d(self, active=True) -> mi.Float:
        return self.rng.next_float32(mi.Bool(active))


#: Vertices of a path whose shadow-ray transmittance the store keeps (at most), and
#: the store's memory cap: past them the replay estimates it again, with the same numbers
STORED_VERTICES, STORE_BYTES = 16, 256 * 2**20
#: The events of a replay's sub-path (tracking/empty_scatter.py) count from here: never
#: stored, their numbers apart from the path's
SUB_PATH_EVENT = 1 << 20
#: Salt of the shadow rays' streams
SALT_STREAM = 0x2545F491


class ShadowStore:
    """The shadow rays' transmittance estimates of one gradient render (both passes):
    the primal pass writes each of a path's first :attr:`slots` emitter samples'
    estimates (:meth:`put`); the replay, which needs them only to know the light
    gathered before each event, reads them (:meth:`get`) instead of walking the
    shadow ray again: 2-7% of a step on the 64^3 cloud (docs/benchmarks.md,
    seventeenth session). Where nothing is stored (later events,
    a sub-path) the replay walks again with the same :class:`ShadowNumbers`, so its
    estimate equals the primal's all the same. Events are the path loop's iterations
    (null surfaces included), the same in both passes.

    Memory: ``slots`` x lanes x channels floats, ``slots`` <= ``max_depth`` and
    :data:`STORED_VERTICES`, the whole at most :data:`STORE_BYTES`."""

    def __init__(self, seed, width: int, max_depth: int):
        self.lane = dr.arange(mi.UInt32, width)
        self.key = lane_keys(self.lane, seed, SALT_STREAM)
        self.slots = self.capacity(width, max_depth)
        self.values = dr.zeros(mi.Spectrum, width * self.slots) if self.slots else None

    @staticmethod
    def capacity(width: int, max_depth: int) -> int:
        """Events stored per lane for ``width`` lanes (0: none, every replay walks)."""
        depth = STORED_VERTICES if max_depth < 0 else min(max_depth, STORED_VERTICES)
        return max(0, min(depth, STORE_BYTES // (4 * dr.size_v(mi.Spectrum) * max(1, width))))

    def numbers(self, event: mi.UInt32) -> ShadowNumbers:
        """The stream of the shadow ray at ``event`` (a per-lane loop counter)."""
        state, sequence = mi.sample_tea_32(self.key, event)
        rng = mi.PCG32()
        rng.seed(mi.UInt64(state) << 32 | mi.UInt64(sequence), mi.UInt64(self.lane))
        return ShadowNumbers(rng)

    def stored(self, event: mi.UInt32) -> mi.Bool:
        return event < self.slots

    def _index(self, event):
        return self.lane * self.slots + event

    def put(self, event: mi.UInt32, T: mi.Spectrum, active) -> None:
        if self.slots:
            dr.scatter(self.values, T, self._index(event), active & self.stored(event))

    def get(self, event: mi.UInt32, active) -> mi.Spectrum:
        """The estimate kept at ``event`` (``active``: lanes where :meth:`stored`)."""
        if not self.slots:
            return mi.Spectrum(0.0)
        return dr.gather(mi.Spectrum, self.values, self._index(event), active)


# -- the transmittance of a shadow ray -------------------------------------------------
def shadow_gradient(replay: Replay, media, medium: mi.MediumPtr, ray: mi.Ray3f,
                    t_max: mi.Float, after: mi.Spectrum, active) -> mi.Spectrum:
    """The transmittance derivative of one piece ``[0, t_max]`` of a shadow ray in each
    lane's medium: analytic in homogeneous media (``-after * d(sigma_t) t_max``),
    :func:`optical_depth_point` in heterogeneous ones. Returns the tangent."""
    def homogeneous(mask):
        def tau():
            _, _, sigma_t = medium.get_scattering_coefficients(medium_interaction(ray, 0.0),
                                                               mask)
            return mi.Spectrum(sigma_t) * t_max
        return replay.transmittance(attached(tau), after, mask)

    def heterogeneous(tracker, mask):
        return optical_depth_point(replay, tracker, ray, t_max, after, mask)
    return media.dispatch(medium, active, mi.Spectrum(0.0), homogeneous, heterogeneous)


#: salt of the hashed number of a shadow ray's point (:func:`optical_depth_point`)
SALT_SHADOW = 0x6C8E9CF5


def optical_depth_point(replay: Replay, tracker, ray: mi.Ray3f, t_max: mi.Float,
                        after: mi.Spectrum, active) -> mi.Spectrum:
    r"""The transmittance derivative of a shadow ray's piece ``[0, t_max]`` in a
    heterogeneous medium, whatever estimated its value: :math:`\partial T = -T \int
    \partial\sigma_t\,ds`, so :math:`-\mathit{after}\,\partial\sigma_t(s)\,l` at one
    point ``s`` uniform over the piece, of length ``l`` (``after``: the emitter sample's
    contribution, detached, ``T`` included). Unbiased wherever :math:`\partial\sigma_t`
    can be non-zero, voxels at 0 included. Where the piece is unbounded (no surface
    ends it), over the medium's box only: the edge voxels' values clamped over an
    infinite stretch beyond it are not differentiated. No walk: points drawn at the
    majorant's rate through the majorant grid cost a step per cell crossed and gave no
    lower variance (docs/benchmarks.md, sixteenth session). Returns the tangent."""
    t_in, t_out = tracker.bounds(ray, t_max)
    bounded = dr.isfinite(t_max)
    start = dr.select(bounded, 0.0, t_in)
    length = dr.select(bounded, t_max, t_out) - start
    active = active & (length > 0)
    s = start + mi.sample_tea_float32(replay.ray_key(ray, SALT_SHADOW), 0, 6) * length

    def term():
        return -after * tracker.sigma_t(medium_interaction(ray, s), active) * length
    return replay.emit(attached(term), active)


# -- free flights ------------------------------------------------------------------------
def interval_optical_depth(replay: Replay, tracker, ray: mi.Ray3f, t: mi.Float,
                           step: mi.Float, active) -> mi.Spectrum:
    """An unbiased, attached estimate of the optical depth of ``[t, t + step]``: one
    point uniform in it (:meth:`Replay.uniform`), ``sigma_t * step``."""
    s = t + replay.uniform(ray, t) * step

    def tau():
        return tracker.sigma_t(medium_interaction(ray, s), active) * step
    return attached(tau)


class FlightGradient:
    """How a replayed free flight through a heterogeneous medium propagates the
    derivative of its transmittance: a rule of ``volpath_delta``'s
    ``gradient_estimator`` (:data:`GRADIENT_ESTIMATORS`), as the transmittance and
    free-flight rules are. A hook returns the tangent it adds, or None where the rule
    adds nothing there (then the kernel holds no code for it)."""
    name = ""
    #: whether the path keeps one matched point (:class:`~mitsuba_plugins.tracking.
    #: empty_scatter.MatchedScatter`) instead of one where ``sigma_t = 0``
    matched = False

    def scattering(self, replay: Replay, real):
        """The real collisions (in a heterogeneous medium) that propagate ``sigma_s``'s
        derivative: all of them (``sm`` takes in-scattering elsewhere on its flights)."""
        return real

    def travel(self, replay: Replay, tracker, ray: mi.Ray3f, t: mi.Float, step: mi.Float,
               after: mi.Spectrum, active):
        """A step ``[t, t + step]`` of the flight, in front of ``after``."""
        return None

    def null_collision(self, replay: Replay, sigma_maj: mi.Float, props, after: mi.Spectrum,
                       active):
        """A null collision (``props``: the medium there, attached), in front of
        ``after``."""
        return None


class DifferentialRatioTracking(FlightGradient):
    r"""``drt``: each step's transmittance :math:`\exp(-\int\sigma_t)` differentiated
    through an unbiased estimate of its optical depth (:func:`interval_optical_depth`);
    null collisions carry no weight to differentiate (Nimier-David et al. 2022)."""
    name = "drt"

    def travel(self, replay, tracker, ray, t, step, after, active):
        moving = active & (step > 0)
        tau = interval_optical_depth(replay, tracker, ray, t, step, moving)
        return replay.transmittance(tau, after, moving)


class DeltaTrackingGradient(FlightGradient):
    r"""``delta``: the delta-tracking estimator differentiated as ``prbvolpath`` does: a
    null collision weighs :math:`\sigma_n(\theta) / \sigma_n`."""
    name = "delta"

    def null_collision(self, replay, sigma_maj, props, after, active):
        sigma_n = attached(lambda: dr.maximum(sigma_maj - props.sigma_t, 0.0))
        return replay.factor(sigma_n, after, active)


class SampleMatching(FlightGradient):
    r"""``sm``: sample matching (Yu, Wang, Ling, Xu and Zhao 2026), one point per path.
    In heterogeneous media a flight's derivative is :math:`\int \partial\sigma_t(s)\,
    [\alpha L_s(s) - L(s)]\,ds` in front of the path so far: the light a denser medium
    scatters toward the path minus the light it blocks, two terms of opposite sign. On
    the camera's flights (depth 0, ``replay.matching``) both are estimated at the same
    point (a reservoir over those flights' points, one sub-path for :math:`L_s`:
    :class:`~mitsuba_plugins.tracking.empty_scatter.MatchedScatter`), so what they share
    cancels, and those flights' steps and real collisions propagate nothing; later
    flights take ``drt``'s terms."""
    name = "sm"
    matched = True

    def scattering(self, replay, real):
        return real & ~replay.matching

    def travel(self, replay, tracker, ray, t, step, after, active):
        # flights sm does not match: drt's terms
        return DifferentialRatioTracking.travel(self, replay, tracker, ray, t, step, after,
                                                active & ~replay.matching)


#: ``gradient_estimator`` (``volpath_delta``): name -> rule
GRADIENT_ESTIMATORS = {rule.name: rule for rule in (DifferentialRatioTracking,
                                                    DeltaTrackingGradient, SampleMatching)}


def replay_homogeneous(replay: Replay, medium: mi.MediumPtr, ray: mi.Ray3f, distance,
                       remaining: mi.Spectrum, active, scattered) -> mi.Spectrum:
    """The derivative of an analytic flight through a homogeneous medium over
    ``distance``: ``exp(-sigma_t d)`` in front of ``remaining``, and ``sigma_s`` at a
    real collision (``scattered``). Returns the tangent."""
    d = dr.select(dr.isfinite(distance), distance, 0.0)    # infinite: T = 0, nothing after

    def coefficient(index: int, factor=1.0):
        def evaluate():
            values = medium.get_scattering_coefficients(medium_interaction(ray, 0.0), active)
            return mi.Spectrum(values[index]) * factor
        return evaluate

    # each attached value is evaluated just before its derivative is propagated (see
    # replay_vertex): forward mode loses part of the tangent of a second value evaluated
    # beside the first (sigma_s beside sigma_t: issue 46)
    grad = replay.transmittance(attached(coefficient(2, d)), remaining, active)
    return grad + replay.factor(attached(coefficient(0)), remaining, scattered)


class GradientPass:
    """The shadow ray's pass in a replay (:func:`mitsuba_plugins.tracking.shadow_rays.shadow_pieces`):
    the transmittance derivative of each piece (:func:`shadow_gradient`) in front of
    ``after``, the emitter sample's detached contribution; ``value`` is the tangent."""

    def __init__(self, replay: Replay, media, after: mi.Spectrum):
        self.replay, self.media, self.after = replay, media, after

    def initial(self):
        return mi.Spectrum(0.0)

    def piece(self, value, medium, ray, t_piece, sampler, active):
        return value + shadow_gradient(self.replay, self.media, medium, ray, t_piece,
                                       self.after, active)

    def surface(self, value, si, bsdf, hit):
        return value

    def goes_on(self, value):
        return mi.Bool(True)

    def roulette(self, value, sampler, going_on):
        """No roulette: the primal's (in ``after``) already decided which rays count."""
        return value


def replay_vertex(replay: Replay, scene, media, ref, ds, shadow_medium, contribution,
                  f_attached, active_em, direction_value, after_vertex,
                  active_next) -> mi.Spectrum:
    """The derivatives at one vertex: the emitter sample (its BSDF / phase value, which
    ``f_attached()`` evaluates, and its shadow ray's transmittance, both in front of the
    detached ``contribution``), then the sampled direction's value
    (``direction_value()``) in front of ``after_vertex``, all the path gathers after this
    vertex. Returns the tangent.

    The values are evaluated here, each just before its derivative is propagated: in
    forward mode ``dr.forward_to`` refuses ("edge ... outside of the current
    dr.isolate_grad() scope") once a second attached evaluation of the same parameter
    (the phase's ``g``, a BSDF's texture) exists before the first is propagated."""
    grad = replay.factor(attached(f_attached), contribution, active_em)
    grad += shadow_pieces(scene, ref, ds, shadow_medium,
                          GradientPass(replay, media, contribution), None,
                          active_em & dr.any(contribution != 0))
    return grad + replay.factor(attached(direction_value), after_vertex, active_next)
