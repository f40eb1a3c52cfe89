"""Invalid-sample accounting: NaN/Inf samples are counted in the kernel and zeroed, for
our integrators (their sample guard) and for any other one (the counting wrapper)."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import assert_same_render, camera, load, render
from mitsuba_plugins.tools import stats
from mitsuba_plugins.validity import counted, take_invalid_samples

RES = 16


class PoisonedIntegrator(mi.SamplingIntegrator):
    """Radiance 1, except NaN (channel 0) or Inf (the last) for camera rays whose first
    sample falls in chosen ranges: a known fraction of invalid samples."""

    def sample(self, scene, sampler, ray, medium=None, active=True):
        u = sampler.next_1d(active)
        L = mi.Spectrum(1.0)
        L[0] = dr.select(u < 0.25, dr.nan, L[0])
        last = dr.size_v(mi.Spectrum) - 1     # 2 in RGB (mono: the NaN channel too)
        L[last] = dr.select((u >= 0.25) & (u < 0.375), dr.inf, L[last])
        return L, mi.Bool(True), []


def test_counting_wrapper_counts_and_zeroes():
    mi.register_integrator("poisoned_test", lambda props: PoisonedIntegrator(props))
    scene = mi.load_dict({"type": "scene", "sensor": camera(res=RES)})
    integrator = counted(mi.load_dict({"type": "poisoned_test"}))
    spp = 64
    img = np.array(mi.render(scene, integrator=integrator, spp=spp, seed=2))
    invalid = take_invalid_samples(integrator)
    n = RES * RES * spp
    # Binomial(n, 0.375): the count lies within 5 sigma of its mean
    assert abs(invalid - 0.375 * n) < 5 * np.sqrt(n * 0.375 * 0.625), invalid
    assert np.isfinite(img).all()
    # the zeroed samples pull each pixel to the valid fraction (box filter)
    assert abs(img.mean() - 0.625) < 0.02
    assert take_invalid_samples(integrator) == 0  # the counter was reset


@pytest.mark.parametrize("name", ["direct_mis", "path_rr", "volpath_delta", "volpath_raymarch"])
def test_our_integrators_count_nan_in_the_scene(name):
    """A BSDF whose reflectance is NaN: every sample that reaches it is invalid, counted
    and zeroed; none of it reaches the image."""
    scene = load("cornell_box", res=RES)
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("reflectance.value"))
    # the stored type: Color3f in RGB, the upsampled model in spectral, Float in mono
    params[key] = type(params[key])(dr.nan)
    params.update()
    integrator = mi.load_dict({"type": name})
    img = np.array(mi.render(scene, integrator=integrator, spp=4, seed=1))
    assert take_invalid_samples(integrator) > 0
    assert np.isfinite(img).all()


def test_render_passes_reports_invalid_samples():
    mi.register_integrator("poisoned_test", lambda props: PoisonedIntegrator(props))
    scene = mi.load_dict({"type": "scene", "sensor": camera(res=4)})
    est = stats.render_passes(scene, 2, 16, integrator=mi.load_dict({"type": "poisoned_test"}),
                              warmup=True)
    assert 0 < est.invalid <= 2 * 16 * 16


def test_builtins_are_counted_without_changing_the_image():
    """The wrapper leaves Mitsuba's own image as it is (up to the film's float-atomic
    summation order)."""
    scene = load("cornell_box", res=RES)
    raw = mi.load_dict({"type": "path"})
    a = np.array(mi.render(scene, integrator=raw, spp=8, seed=3))
    b = render(scene, raw, spp=8, seed=3)
    assert_same_render(b, a)
