"""Gradient checks: derivatives of a render's mean along parameter directions, by our
integrators' gradient renders (backward and forward mode) and by central finite
differences of the primal render with common random numbers (the same seed on both
sides). Used by tests/integrators/test_gradients.py and benchmarks/inverse.py.

A *direction* maps parameter keys of ``mi.traverse(scene)`` to arrays of their shape
(or scalars). The derivative of ``mean(image)`` along it is ``<grad, direction>``.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def _value(params, key):
    value = params[key]
    return type(value)(value)


def _as(value, direction):
    """``direction`` as an array of ``value``'s type."""
    if isinstance(value, mi.TensorXf):
        return mi.TensorXf(np.asarray(direction, np.float32).reshape(value.shape))
    return type(value)(direction)


def backward_derivatives(scene, params, direction: dict, integrator, seed: int, spp: int,
                         weights=None) -> dict:
    """``{key: <d mean(image) / d params[key], direction[key]>}`` from one backward-mode
    gradient render with every key of ``direction`` differentiable; ``weights`` (an
    image of the film's shape): of ``mean(weights * image)`` instead."""
    originals = {k: _value(params, k) for k in direction}
    for key in direction:
        dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, integrator=integrator, spp=spp, seed=seed)
    target = img if weights is None else img * mi.TensorXf(np.asarray(weights, np.float32))
    dr.backward(dr.mean(target, axis=None))
    out = {}
    for key, d in direction.items():
        grad = np.array(dr.grad(params[key]), np.float64)
        out[key] = float(np.sum(grad * np.asarray(d, np.float64)))
        params[key] = originals[key]
    params.update()
    return out


def forward_image(scene, params, direction: dict, integrator, seed: int, spp: int):
    """The forward-mode derivative image along ``direction`` (numpy)."""
    originals = {k: _value(params, k) for k in direction}
    for key in direction:
        dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, integrator=integrator, spp=spp, seed=seed)
    # as dr.forward(params[key]) does: every variable reachable from the parameters
    # takes its tangent in creation order (values derived at params.update(), such as
    # grid_medium's folded scale, before the render; dr.forward_to(img) would visit
    # only the render's own inputs)
    for key, d in direction.items():
        dr.set_grad(params[key], _as(params[key], d))
        dr.enqueue(dr.ADMode.Forward, params[key])
    dr.traverse(dr.ADMode.Forward)
    out = np.array(dr.grad(img))
    for key in direction:
        params[key] = originals[key]
    params.update()
    return out


def theta_derivatives(scene, params, key: str, integrator, seed: int, spp: int) -> tuple:
    """``(forward, backward)``: d mean(image) / d theta with ``params[key] = value +
    theta`` at theta = 0, as Mitsuba's own AD integrator tests write it (the tangent
    pushed through ``params.update()`` by ``dr.forward(theta)``, then
    ``render_forward(params=theta)``; ``render_backward`` of the mean's adjoint). Both
    passes draw the same numbers: the two agree to float rounding."""
    original = _value(params, key)
    out = []
    for mode in ("forward", "backward"):
        theta = mi.Float(0.0)
        dr.enable_grad(theta)
        params[key] = original + theta
        params.update()
        if mode == "forward":
            dr.forward(theta, dr.ADFlag.ClearEdges)
            img = integrator.render_forward(scene, params=theta, seed=seed, spp=spp)
            out.append(float(np.mean(np.array(img, np.float64))))
        else:
            with dr.suspend_grad():      # the image's shape (channels: the variant's)
                shape = integrator.render(scene, seed=seed, spp=1).shape
            weights = dr.full(mi.TensorXf, 1.0 / float(np.prod(shape)), shape)
            integrator.render_backward(scene, params, weights, seed=seed, spp=spp)
            out.append(float(dr.grad(theta)[0]))
        params[key] = original
        params.update()
    return tuple(out)


def primal_mean(scene, params, direction: dict, step: float, integrator, seed: int,
                spp: int, weights=None) -> float:
    """``mean(image)`` at ``theta + step * direction``."""
    originals = {k: _value(params, k) for k in direction}
    for key, d in direction.items():
        value = originals[key]
        params[key] = value + _as(value, np.asarray(d, np.float32) * step)
    params.update()
    img = np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed), np.float64)
    for key in direction:
        params[key] = originals[key]
    params.update()
    return float(np.mean(img if weights is None else img * weights))


def finite_difference(scene, params, direction: dict, h: float, integrator, seed: int,
                      spp: int, weights=None, one_sided: bool = False) -> float:
    """Richardson-extrapolated central difference along ``direction`` with common random
    numbers: ``(4 D(h) - D(2h)) / 3`` (error O(h^4)), ``D(h) = (f(+h) - f(-h)) / 2h``.
    ``one_sided`` (a parameter at a bound, e.g. a density at 0): ``(4 f(h) - 3 f(0) -
    f(2h)) / 2h`` (error O(h^2))."""
    steps = (0.0, h, 2 * h) if one_sided else (-2 * h, -h, h, 2 * h)
    f = {s: primal_mean(scene, params, direction, s, integrator, seed, spp, weights)
         for s in steps}
    if one_sided:
        return (4 * f[h] - 3 * f[0.0] - f[2 * h]) / (2 * h)
    d1 = (f[h] - f[-h]) / (2 * h)
    d2 = (f[2 * h] - f[-2 * h]) / (4 * h)
    return (4 * d1 - d2) / 3


def welch(a, b) -> tuple:
    """Welch's t-test of two samples' means: ``(t, p)`` (two-sided; p = 1 for two equal
    constant samples, 0 for two different ones)."""
    from scipy import stats
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.var() == 0 and b.var() == 0:
        return (0.0, 1.0) if a.mean() == b.mean() else (np.inf, 0.0)
    result = stats.ttest_ind(a, b, equal_var=False)
    return float(result.statistic), float(result.pvalue)


def smooth_direction(shape, seed=0) -> np.ndarray:
    """A smooth random field of ``shape`` in [0.2, 1] (a blurred Gaussian field): a
    direction for the derivative along a density grid."""
    from scipy.ndimage import gaussian_filter
    v = gaussian_filter(np.random.default_rng(seed).normal(size=shape), 1.0)
    return 0.6 + 0.4 * v / np.abs(v).max()
