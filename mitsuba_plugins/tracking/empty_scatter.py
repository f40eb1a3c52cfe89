r"""The light a new density would scatter where there is none: the in-scattering term of
a gradient replay at points where ``sigma_t = 0`` (issue 48; docs/method.md section 11).

A free flight estimates :math:`\int_0^{t} T(s)\,\sigma_s(s)\,L_s(s)\,ds` (plus the
transmittance to its end) by drawing real collisions in proportion to
:math:`T\sigma_t`; the replay differentiates it through the factor
:math:`\sigma_s(\theta)/\sigma_s` at each real collision. Where :math:`\sigma_t = 0` no real
collision is ever drawn, yet :math:`\partial\sigma_s` is not 0 there (a density grid's
voxels at 0): the term :math:`\int_{\sigma_t = 0} T\,\partial\sigma_s\,L_s\,ds` had no
estimator (issue 26's documented bias; at max_depth 2 on the smoke with empty slabs,
-0.167 against finite differences' -0.081).

Its estimator here, per path:

* **candidates**: each flight through a heterogeneous medium (where the path may still
  scatter: ``depth + 1 < max_depth``) draws one point ``s`` uniform over the part of the
  flight inside the medium's grid bounds, of length ``l``; the point is a candidate where
  every channel of ``sigma_t`` is exactly 0. The path passed ``s`` (delta tracking goes
  on through a point with weight 1 and probability :math:`T`: the track-length
  argument), so ``beta l dsigma_s(s) L_s(s)`` estimates the flight's share of the term;
* **one per path**: a reservoir over the path's candidates with weights ``w = l
  mean(beta)`` keeps one (``W`` their sum); the term is ``W beta / mean(beta) dsigma_s
  L_s`` at the kept point, unbiased for the sum over candidates;
* ``L_s``, the light scattered at the kept point toward the path, by a sub-path that
  starts with a real collision there (emitter sample, phase-sampled continuation, MIS,
  the path's remaining depth). It is the same path loop going on after the path ends
  (:func:`mitsuba_plugins.volume_loop.trace_volumes`): no second copy of the loop in the
  kernel, and the replay of the path itself is over, so the sampler's further numbers
  change nothing of it. The sub-path's own events propagate nothing (the adjoint is 0
  on its lanes, :meth:`EmptyScatter.silence`; forward tangents are put back,
  :meth:`EmptyScatter.end`).

Gray heterogeneous media only: in a chromatic one the throughput changes at null
collisions (spectral MIS), which this one-point-per-flight estimate does not follow
(:func:`applies`). Medium emission a new density would add where the majorant is 0 is
not estimated either (docs/usage.md, Gradients).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.tracking.replay import attached
from mitsuba_plugins.tracking.trackers import medium_interaction

VARIANT = mi.variant()

#: the smallest weight per unit length of a sample-matching candidate, as a fraction of
#: the medium's largest extinction (:meth:`MatchedScatter.density_weight`)
FLOOR = 0.05

#: salts of the hashed numbers of a flight's point and of the reservoir's choice
SALT_POINT, SALT_CHOICE = 0x51ED270B, 0x2545F491


def applies(media) -> bool:
    """Whether the replay of a scene with these media carries the term: some gray
    heterogeneous medium."""
    return bool(media.heterogeneous) and not media.chromatic_heterogeneous


class EmptyScatter:
    """The reservoir of one path (loop state of the replay): ``W`` the candidates' weight
    so far and the kept one's point ``p``, the flight's direction ``d``, throughput
    ``beta``, ``depth`` and ``medium``; then ``sub`` (the lane runs the sub-path) and
    what the path had gathered when it ended (``L``, ``valid``, ``grad``)."""
    DRJIT_STRUCT = {"W": mi.Float, "p": mi.Point3f, "d": mi.Vector3f, "beta": mi.Spectrum,
                    "depth": mi.UInt32, "medium": mi.MediumPtr, "sub": mi.Bool,
                    "L": mi.Spectrum, "valid": mi.Bool, "grad": mi.Spectrum}

    def __init__(self, W=None, p=None, d=None, beta=None, depth=None, medium=None,
                 sub=None, L=None, valid=None, grad=None):
        self.W, self.p, self.d, self.beta, self.depth, self.medium = W, p, d, beta, depth, medium
        self.sub, self.L, self.valid, self.grad = sub, L, valid, grad

    @staticmethod
    def empty() -> "EmptyScatter":
        return EmptyScatter(mi.Float(0.0), mi.Point3f(0.0), mi.Vector3f(0.0, 0.0, 1.0),
                            mi.Spectrum(0.0), mi.UInt32(0), dr.zeros(mi.MediumPtr),
                            mi.Bool(False), mi.Spectrum(0.0), mi.Bool(False),
                            mi.Spectrum(0.0))

    def density_weight(self, tracker, sigma_t: mi.Spectrum, matching) -> mi.Float:
        """A candidate's weight per unit length and throughput at a point of this
        extinction: 1 where it is 0 in every channel (the candidates), else 0."""
        return dr.select(dr.all(sigma_t == 0.0), 1.0, 0.0)

    def consider(self, replay, media, medium: mi.MediumPtr, ray: mi.Ray3f, t_end: mi.Float,
                 beta: mi.Spectrum, depth: mi.UInt32, scatters, after: mi.Spectrum,
                 active, matching=False) -> "EmptyScatter":
        """The flight of ``ray`` over ``[0, t_end]`` in ``medium``, entered with ``beta``
        at ``depth`` (``scatters``: the path may scatter in it), ``after`` the light the
        path gathers from the flight's start on: its candidate (if any) enters the
        reservoir (not in sub-paths). ``matching``: lanes whose flight a subclass
        treats otherwise (:class:`MatchedScatter`)."""
        active = active & ~self.sub & scatters
        u_point = replay.uniform(ray, mi.Float(SALT_POINT))
        u_choice = replay.uniform(ray, mi.Float(SALT_CHOICE))

        def heterogeneous(tracker, mask):
            t_in, t_out = tracker.bounds(ray, t_end)
            length = dr.maximum(t_out - t_in, 0.0)
            s = t_in + u_point * length
            rho = self.density_weight(tracker, tracker.sigma_t(medium_interaction(ray, s), mask),
                                      matching)
            return mi.Vector3f(dr.select(mask & (length > 0), length * rho, 0.0), s, rho)
        weight, s, rho = media.dispatch(medium, active & dr.isfinite(t_end), mi.Vector3f(0.0),
                                        lambda mask: mi.Vector3f(0.0), heterogeneous)
        w = weight * dr.mean(beta)
        candidate = active & (w > 0)
        self.W = dr.select(candidate, self.W + w, self.W)
        take = candidate & (u_choice * self.W < w)
        self.p = dr.select(take, ray(s), self.p)
        self.d = dr.select(take, ray.d, self.d)
        self.beta = dr.select(take, beta, self.beta)
        self.depth = dr.select(take, depth, self.depth)
        self.medium = dr.select(take, medium, self.medium)
        self.keep(take, after, rho)
        return self

    def keep(self, take, after, rho) -> None:
        """What else the reservoir keeps of a chosen candidate (nothing here)."""

    def silence(self, replay, dL: mi.Spectrum) -> None:
        """The adjoint of this iteration: 0 on lanes that run their sub-path (backward
        mode; forward mode has none)."""
        if dL is not None:
            replay.dL = dr.select(self.sub, 0.0, dL)

    def restart(self, active, L, valid, grad) -> mi.Bool:
        """The lanes whose path has just ended and kept a point: they keep what the path
        gathered and run the sub-path next (the caller sets its start)."""
        go = ~active & ~self.sub & (self.W > 0)
        self.L = dr.select(go, L, self.L)
        self.valid = dr.select(go, valid, self.valid)
        self.grad = dr.select(go, grad, self.grad)
        self.sub |= go
        return go

    def end(self, L, valid, grad):
        """After the loop: ``(L_s, L, valid, grad)``, the sub-path's light and the path's
        own values back."""
        L_s = dr.select(self.sub, L, 0.0)
        L_s = dr.select(dr.all(dr.isfinite(L_s)), L_s, 0.0)
        return (L_s, dr.select(self.sub, self.L, L), dr.select(self.sub, self.valid, valid),
                dr.select(self.sub, self.grad, grad))

    def finish(self, replay, media, L_s: mi.Spectrum, active) -> mi.Spectrum:
        """The term at the kept point, propagated (returns the forward-mode tangent)."""
        lanes = active & self.sub & dr.any(L_s != 0)
        ray = mi.Ray3f(self.p, self.d)
        scale = self.W * self.beta / dr.select(dr.mean(self.beta) > 0, dr.mean(self.beta), 1.0)

        def term():
            def sigma_s(tracker, mask):
                return tracker.properties(medium_interaction(ray, 0.0), mask).sigma_s
            return scale * L_s * media.call(self.medium, sigma_s, lanes)
        return replay.emit(attached(term), lanes)


class MatchedScatter(EmptyScatter):
    r"""``gradient_estimator = "sm"`` (sample matching, one point per path): every
    point of the camera's flights (depth 0) through a gray heterogeneous medium is a
    candidate (weight ``l mean(beta) rho``, ``rho`` from :meth:`density_weight`), and the
    kept one also keeps ``after``, the light the path gathered from its flight's start
    on. At the end both halves of the extinction derivative are taken there,
    ``W / (mean(beta) rho) (beta dsigma_s L_s - dsigma_t after)``: what a denser medium
    scatters toward the path and what it blocks of the light behind (the path passed the
    point: the track-length argument, as above). They replace those flights' steps' and
    real collisions' terms of ``drt`` (:class:`~mitsuba_plugins.tracking.replay.
    SampleMatching`); unbiased for the same sum, and what the two halves share cancels
    at the one point. Later flights' points where ``sigma_t = 0`` are candidates of the
    same reservoir for :class:`EmptyScatter`'s term (``after = 0``, ``rho = 1``). Not for
    emitting media (``after`` would hold the emission gathered before the point,
    :func:`check`)."""
    DRJIT_STRUCT = dict(EmptyScatter.DRJIT_STRUCT, after=mi.Spectrum, rho=mi.Float)

    def __init__(self, *args, after=None, rho=None, **kwargs):
        super().__init__(*args, **kwargs)
        self.after, self.rho = after, rho

    @staticmethod
    def empty() -> "MatchedScatter":
        base = EmptyScatter.empty()
        return MatchedScatter(*(getattr(base, k) for k in EmptyScatter.DRJIT_STRUCT),
                              after=mi.Spectrum(0.0), rho=mi.Float(1.0))

    def density_weight(self, tracker, sigma_t: mi.Spectrum, matching) -> mi.Float:
        """On a matched flight the extinction, at least :data:`FLOOR` times the
        medium's largest (the derivative of a density grid is mostly where the density
        is: an optimiser's step, a scale, an albedo; the floor keeps every point a
        candidate); on the others :class:`EmptyScatter`'s."""
        return dr.select(matching, dr.maximum(dr.mean(sigma_t), FLOOR * tracker.grid.outside),
                         super().density_weight(tracker, sigma_t, matching))

    def consider(self, replay, media, medium, ray, t_end, beta, depth, scatters, after,
                 active, matching=False) -> "MatchedScatter":
        # the camera's flights (depth 0) are matched: every point a candidate, even
        # where the path may scatter no more (their transmittance matters), and both
        # halves; later ones are EmptyScatter's (in-scattering where sigma_t = 0 only:
        # no attenuation half, after = 0)
        matching = replay.matching
        return super().consider(replay, media, medium, ray, t_end, beta, depth,
                                matching | scatters, dr.select(matching, after, 0.0), active,
                                matching)

    def keep(self, take, after, rho) -> None:
        self.after = dr.select(take, after, self.after)
        self.rho = dr.select(take, rho, self.rho)

    def finish(self, replay, media, L_s: mi.Spectrum, active) -> mi.Spectrum:
        lanes = active & self.sub
        ray = mi.Ray3f(self.p, self.d)
        mean = dr.mean(self.beta) * self.rho
        norm = self.W / dr.select(mean > 0, mean, 1.0)

        def term():
            def difference(tracker, mask):
                props = tracker.properties(medium_interaction(ray, 0.0), mask)
                return norm * (self.beta * props.sigma_s * L_s - props.sigma_t * self.after)
            return media.call(self.medium, difference, lanes)
        return replay.emit(attached(term), lanes)


def refused(media) -> bool:
    """Whether ``sm`` would be wrong in these media: a chromatic or emitting
    heterogeneous one."""
    return media.chromatic_heterogeneous or media.emission


def matches(media) -> bool:
    """Whether ``sm`` applies to these media and changes anything: some heterogeneous
    medium, none :func:`refused`."""
    return media.heterogeneous and not refused(media)


def resolve(estimator: str, media) -> str:
    """The rule a replay through these media uses for ``gradient_estimator``:
    ``auto`` is ``sm`` where it :func:`matches` (it reconstructs faster than ``drt``:
    docs/benchmarks.md), else ``drt``; any other name is itself."""
    if estimator != "auto":
        return estimator
    return "sm" if matches(media) else "drt"


def check(media) -> None:
    """Refuse ``sm`` where it would be wrong, in one line."""
    if refused(media):
        raise ValueError("volpath_delta: gradient_estimator='sm' needs gray, non-emitting "
                         "heterogeneous media (this scene has a chromatic or emitting one); "
                         "allowed here: 'auto', 'drt', 'delta'")


def for_replay(replay, media):
    """The reservoir of a replay through these media, or None: :class:`MatchedScatter`
    for ``sm``, else :class:`EmptyScatter` where it :func:`applies`."""
    if replay is None:
        return None
    if replay.flight.matched:
        check(media)
        return MatchedScatter.empty() if media.heterogeneous else None
    return EmptyScatter.empty() if applies(media) else None
