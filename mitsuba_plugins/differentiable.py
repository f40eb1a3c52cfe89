"""``render_forward`` / ``render_backward`` of ``volpath_delta`` (Mitsuba's ``ADIntegrator``
interface, so ``mi.render(scene, params, ...)`` with ``dr.backward`` / ``dr.forward``
works as with ``prb``): Mitsuba's ``RBIntegrator`` scaffolding (film, ray generation,
splatting and its adjoint) around our path loop run twice, primal then replay
(:mod:`mitsuba_plugins.tracking.replay`)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.loop_state import traced_once
from mitsuba_plugins.tracking import empty_scatter
from mitsuba_plugins.tracking.replay import Replay, ShadowStore
from mitsuba_plugins.tracking.scene_media import SceneMedia
from mitsuba_plugins.volume_loop import trace_volumes

VARIANT = mi.variant()

_common = mi.ad.integrators.common


class ReplayRender:
    """What ``RBIntegrator.render_forward`` / ``render_backward`` call on ``self``, for
    one render of ``integrator`` from ``sensor``: Mitsuba's ``prepare`` and
    ``sample_rays``, and :meth:`sample` (the primal pass and the replay)."""
    prepare = _common.ADIntegrator.prepare
    sample_rays = _common.ADIntegrator.sample_rays

    def __init__(self, integrator, sensor: mi.Sensor, seed):
        self.integrator, self.sensor, self.seed = integrator, sensor, seed

    def aov_names(self):
        return []

    def sample(self, mode, scene, sampler, ray, δL=None, state_in=None, active=True,
               **kwargs):
        integrator = self.integrator
        media = SceneMedia(scene)
        medium = self.sensor.get_medium()
        medium = dr.zeros(mi.MediumPtr) if medium is None else mi.MediumPtr(medium)
        active = mi.Bool(active)
        if mode == dr.ADMode.Primal:
            self.shadows = ShadowStore(self.seed, dr.width(ray), integrator.max_depth)
            with traced_once():
                L, valid = trace_volumes(integrator, integrator.strategy, scene, sampler,
                                         ray, medium, media, active, shadows=self.shadows)
            L = integrator.sample_guard(L, active)      # NaN/Inf counted, as in primal renders
            return L, valid, [], (L, valid)
        L_primal, _ = state_in
        # the primal pass runs as a kernel of its own: the replay reads what it stored
        dr.eval(L_primal, self.shadows.values)
        # lanes the primal pass zeroed for NaN/Inf carry no derivative; lanes with no
        # valid ray (nothing hit, emitters hidden) still do: a denser medium on their
        # flights would scatter light toward them (the sub-path terms of
        # tracking/empty_scatter.py), while every other term of theirs is 0 (L = 0)
        keep = dr.all(dr.isfinite(L_primal))
        dL = None if δL is None else dr.select(keep, δL, 0.0)
        replay = Replay(mode, dL, dr.select(keep, L_primal, 0.0), self.seed,
                        empty_scatter.resolve(integrator.gradient_estimator, media))
        with traced_once():
            L, valid, grad = trace_volumes(integrator, integrator.strategy, scene, sampler,
                                           ray, medium, media, active & keep, replay,
                                           shadows=self.shadows)
        if mode == dr.ADMode.Forward:
            return integrator.sample_guard(dr.select(keep, grad, 0.0), active), valid, [], None
        return L, valid, [], None


def _sensor(scene, sensor):
    return scene.sensors()[sensor] if isinstance(sensor, int) else sensor


#: Parameters of these objects that the replay differentiates (their other parameters:
#: positions, transforms, emitted radiance, sensor settings are not)
_DIFFERENTIATED = {"shape": ("bsdf.", "interior_medium.", "exterior_medium."),
                   "sensor": ("medium.",), "emitter": ()}


def undifferentiated(scene) -> list:
    """Names of gradient-enabled parameters whose derivatives the replay does not
    propagate (emitters, shapes' geometry and transforms, sensors): their gradient
    would be silently 0."""
    found = []
    kinds = (("emitter", scene.emitters()), ("shape", scene.shapes()),
             ("sensor", scene.sensors()))
    for kind, objects in kinds:
        for obj in objects:
            params = mi.traverse(obj)
            for key in params.keys():
                if key.startswith(_DIFFERENTIATED[kind]):
                    continue
                try:
                    enabled = dr.grad_enabled(params[key])
                except (TypeError, RuntimeError):
                    enabled = False
                if enabled:
                    found.append(f"{obj.id() or obj.class_name()}.{key}")
    return found


def check(integrator, scene) -> None:
    """Refuse, in one line, a gradient render whose derivatives would be silently 0 or
    are not implemented."""
    integrator.check_gradients()
    missing = undifferentiated(scene)
    if missing:
        raise NotImplementedError(
            f"{integrator.NAME}: gradients with respect to {', '.join(missing)} are not "
            "computed (emitters, shapes' geometry and sensors are not differentiated; use "
            "Mitsuba's 'prb' or 'prb_projective' for those)")


def render_forward(integrator, scene, params, sensor=0, seed=0, spp=0):
    """Forward-mode derivative image (``RBIntegrator.render_forward``)."""
    check(integrator, scene)
    sensor = _sensor(scene, sensor)
    return _common.RBIntegrator.render_forward(ReplayRender(integrator, sensor, seed), scene,
                                               params, sensor, seed, spp)


def render_backward(integrator, scene, params, grad_in, sensor=0, seed=0, spp=0):
    """Accumulate ``grad_in`` into the parameters' gradients
    (``RBIntegrator.render_backward``)."""
    check(integrator, scene)
    sensor = _sensor(scene, sensor)
    return _common.RBIntegrator.render_backward(ReplayRender(integrator, sensor, seed), scene,
                                                params, grad_in, sensor, seed, spp)
