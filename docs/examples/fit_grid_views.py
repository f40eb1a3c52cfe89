"""Recover grid_medium's whole density grid from several views, one backward per step
(docs/usage.md, Gradients: "Several views per step"). Run from the repository root:
``.venv/bin/python docs/examples/fit_grid_views.py``. Benchmarks of the same kind, against
Mitsuba's prbvolpath: benchmarks/inverse.py (``reconstruct``) and
benchmarks/optimisation_step.py (the time of one step)."""
import math

import drjit as dr
import mitsuba as mi

import mitsuba_plugins  # noqa: F401  -- picks libLLVM, registers the plugins

mi.set_variant("llvm_ad_rgb")
from mitsuba_plugins.tools.scenes import camera, grid, media_scene  # noqa: E402

# the smoke (48^3 voxels) in a ball, a small light, a dim environment
scene = media_scene(grid(scale=8.0, albedo=0.85), env=0.1)
params = mi.traverse(scene)
key = "ball.interior_medium.data"
truth = mi.TensorXf(params[key])

# six cameras around it, 32x32 pixels each
sensors = [mi.load_dict(camera(res=32, origin=(4 * math.sin(a), 0.8 if i % 2 else -0.2,
                                               4 * math.cos(a))))
           for i, a in enumerate(2 * math.pi * k / 6 for k in range(6))]
# emitters hidden: pixels that see the small light would dominate the loss
integrator = mi.load_dict({"type": "volpath_delta", "max_depth": 8, "hide_emitters": True})
references = [mi.render(scene, sensor=s, integrator=integrator, spp=256, seed=7)
              for s in sensors]


def grid_error():
    return (dr.sqrt(dr.sum(dr.square(params[key] - truth), axis=None) /
                    dr.sum(dr.square(truth), axis=None))).array[0]


params[key] = dr.full(mi.TensorXf, dr.mean(truth, axis=None).array[0], truth.shape)
params.update()
print(f"start: grid error {grid_error():.3f}")
opt = mi.ad.Adam(lr=0.02)
opt[key] = params[key]
params.update(opt)
for it in range(60):
    # every view's render joins one loss; one dr.backward runs each render's replay
    loss = 0.0
    for v, sensor in enumerate(sensors):
        img = mi.render(scene, params, sensor=sensor, integrator=integrator, spp=8,
                        seed=it * len(sensors) + v)
        loss += dr.mean(dr.square(img - references[v]), axis=None)
    dr.backward(loss)
    opt.step()
    opt[key] = dr.maximum(opt[key], 0.0)                 # density >= 0
    params.update(opt)
    if it % 10 == 9:
        print(f"iteration {it + 1}: loss {loss.array[0]:.3e}, grid error {grid_error():.3f}")
