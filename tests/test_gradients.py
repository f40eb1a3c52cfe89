"""Issue 14.7: differentiating a render through our integrators raises one line naming
Mitsuba's integrator for gradients (their gradients would be silently wrong: measured
before, d(mean)/d(density) was -5.9e-12 with volpath_delta and -1.1e-4 with
volpath_raymarch where prbvolpath gives +5.4e-4); a primal render with gradient-enabled
parameters still works."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import camera, grid, load, media_scene

CASES = {"direct_mis": "prb", "path_rr": "prb", "volpath_delta": "prbvolpath",
         "volpath_raymarch": "prbvolpath"}


def _scene_and_key(name):
    if name.startswith("volpath"):
        scene = media_scene(grid(), sensor=camera(res=8))
        suffix = ".albedo.value.value"
    else:
        scene = load("cornell_box", res=8)
        suffix = ".reflectance.value"
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith(suffix))
    return scene, params, key


def _messages(error: BaseException) -> str:
    text = []
    while error is not None:
        text.append(str(error))
        error = error.__cause__ or error.__context__
    return " | ".join(text)


@pytest.mark.parametrize("mode", ["backward", "forward"])
@pytest.mark.parametrize("name", list(CASES))
def test_differentiating_our_render_is_refused(name, mode):
    scene, params, key = _scene_and_key(name)
    integrator = mi.load_dict({"type": name} if name == "direct_mis" else
                              {"type": name, "max_depth": 4})
    dr.enable_grad(params[key])
    params.update()
    with pytest.raises(Exception) as info:
        img = mi.render(scene, params, integrator=integrator, spp=4)
        if mode == "backward":
            dr.backward(dr.mean(img, axis=None))
        else:
            dr.forward(params[key])
            dr.grad(img)
    assert (f"{name}: differentiable rendering is not supported (its gradients would be "
            f"wrong); render the gradient with Mitsuba's '{CASES[name]}' integrator"
            in _messages(info.value))


def test_primal_render_with_grad_enabled_parameters_still_works():
    scene, params, key = _scene_and_key("volpath_delta")
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, integrator=mi.load_dict({"type": "volpath_delta"}), spp=4)
    assert np.all(np.isfinite(np.array(img))) and np.array(img).mean() > 0


def test_prbvolpath_gradient_equals_heterogeneous(tmp_path):
    """d(mean image)/d(density grid) with Mitsuba's prbvolpath: grid_medium (dense storage,
    'data' exposed as differentiable) gives what heterogeneous + gridvolume gives."""
    from mitsuba_plugins import gridio
    rng = np.random.default_rng(1)
    gridio.write_vol(tmp_path / "g.vol", rng.uniform(0.5, 2.0, (8, 8, 8, 1)).astype(np.float32))
    to_world = mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)
    media = {
        "grid_medium": {"type": "grid_medium", "filename": str(tmp_path / "g.vol"),
                        "albedo": 0.8, "to_world": to_world},
        "heterogeneous": {"type": "heterogeneous", "albedo": 0.8, "sigma_t": {
            "type": "gridvolume", "filename": str(tmp_path / "g.vol"), "to_world": to_world}}}
    grads = {}
    for kind, medium in media.items():
        scene = mi.load_dict({
            "type": "scene", "env": {"type": "constant"},
            "box": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium},
            "sensor": camera(res=16)})
        params = mi.traverse(scene)
        key = next(k for k in params.keys() if k.endswith("data"))
        dr.enable_grad(params[key])
        params.update()
        img = mi.render(scene, params, integrator=mi.load_dict({"type": "prbvolpath",
                                                                "max_depth": 8}),
                        spp=64, seed=1)
        dr.backward(dr.mean(img, axis=None))
        grads[kind] = np.array(dr.grad(params[key])).ravel()
    a, b = grads["grid_medium"], grads["heterogeneous"]
    assert abs(b.sum()) > 1e-3
    np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-4 * np.abs(b).max())
