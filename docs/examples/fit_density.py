"""Recover grid_medium's density scale from a rendered "photograph" with volpath_delta's
gradients (docs/usage.md, Gradients). Run from the repository root:
``.venv/bin/python docs/examples/fit_density.py``. A whole density grid from several
views: benchmarks/inverse.py (``reconstruct``)."""
import drjit as dr
import mitsuba as mi

import mitsuba_plugins  # noqa: F401  -- picks libLLVM, registers the plugins

mi.set_variant("llvm_ad_rgb")

scene = mi.load_file("scenes/smoke.xml", res="32")
params = mi.traverse(scene)
key = next(k for k in params.keys() if k.endswith("interior_medium.scale"))
truth = float(params[key][0])
reference = mi.render(scene, spp=256)                   # the "photograph"

params[key] = mi.Float(0.5 * truth)                     # a wrong starting value
params.update()
opt = mi.ad.Adam(lr=0.1)
opt[key] = params[key]
params.update(opt)
integrator = mi.load_dict({"type": "volpath_delta", "max_depth": 8})
for it in range(50):
    img = mi.render(scene, params, integrator=integrator, spp=16, seed=it)
    loss = dr.mean(dr.square(img - reference), axis=None)
    dr.backward(loss)
    opt.step()
    opt[key] = dr.maximum(opt[key], 0.0)                 # scale >= 0
    params.update(opt)
    print(f"iteration {it:2d}: loss {loss.array[0]:.2e}, scale {params[key][0]:.3f} "
          f"(true {truth:g})")
