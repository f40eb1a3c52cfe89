"""Every symbolic loop of our integrators records its body once per trace
(``loop_state.widened``): Dr.Jit records a loop a second time to drop a state variable that
the body leaves unchanged and that is narrower than the loop, which doubled the Python
tracing of each render and of each gradient replay (measured: an optimisation step of 6
views at 32^2 x 8 spp, 323 -> 267 ms, kernels unchanged)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import pytest

from helpers import camera, grid, media_scene
from mitsuba_plugins import guided_render
from mitsuba_plugins.tools.scenes import homogeneous

CASES = {
    "homogeneous": ("homogeneous", {"type": "volpath_delta"}),
    "homogeneous_guided": ("homogeneous", {"type": "volpath_delta", "guiding": "volumes"}),
    "grid": ("grid", {"type": "volpath_delta"}),
    "grid_raymarch": ("grid", {"type": "volpath_raymarch"}),
    "surfaces": ("surfaces", {"type": "path_rr"}),
    "surfaces_guided": ("surfaces", {"type": "path_rr", "guiding": "surfaces"}),
}


def scene_of(kind: str):
    if kind == "homogeneous":
        return media_scene(homogeneous(1.0, albedo=0.9, g=0.5), sensor=camera(res=8))
    if kind == "grid":
        return media_scene(grid(), sensor=camera(res=8))
    return media_scene(sensor=camera(res=8))


@pytest.fixture
def body_traces(monkeypatch):
    """Per ``dr.while_loop`` call (loop label), how many times its body was recorded."""
    calls = []
    original = dr.while_loop

    def counting(state, cond, body, *args, **kwargs):
        n = [0]

        def counted(*a):
            n[0] += 1
            return body(*a)
        out = original(state, cond, counted, *args, **kwargs)
        calls.append((kwargs.get("label"), n[0]))
        return out
    monkeypatch.setattr(dr, "while_loop", counting)
    return calls


@pytest.mark.parametrize("case", CASES)
def test_every_loop_body_is_recorded_once(case, body_traces, monkeypatch):
    monkeypatch.setattr(guided_render, "MIN_TRAINING_PATHS", 0)   # guided passes at 8x8
    kind, integrator = CASES[case]
    dr.eval(mi.render(scene_of(kind), integrator=mi.load_dict(integrator), spp=4, seed=1))
    assert body_traces, "no symbolic loop was traced"
    twice = [(label, n) for label, n in body_traces if n != 1]
    assert not twice, f"{case}: loop bodies recorded more than once: {twice}"


def test_gradient_replay_loops_are_recorded_once(body_traces):
    """A gradient render of a density grid (primal, then the replay in backward mode)."""
    scene = media_scene(grid(), sensor=camera(res=8))
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("data"))
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, integrator=mi.load_dict({"type": "volpath_delta",
                                                            "max_depth": 4}), spp=4, seed=1)
    dr.backward(dr.mean(img, axis=None))
    dr.eval(dr.grad(params[key]))
    labels = {label for label, _ in body_traces}
    assert "volpath_delta" in labels and len(body_traces) >= 2
    twice = [(label, n) for label, n in body_traces if n != 1]
    assert not twice, f"loop bodies recorded more than once: {twice}"
