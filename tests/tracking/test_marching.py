"""The ray-marching building blocks alone (mitsuba_plugins.tracking.marching): closed forms,
cell sampling (t-tests against the integral it estimates), the cells' tiling, the
marched transmittance's bias against a converged optical depth, and that a new step
size reuses the compiled kernel."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import SMOKE, SPARSE, camera, exact_optical_depth, grid, media_scene, spectra_of
from mitsuba_plugins.tools import stats
from mitsuba_plugins.tracking import marching, trackers


def test_exp_integral_and_cell_integral():
    x = np.array([0.0, 1e-8, 1e-4, 9.9e-4, 1.1e-3, 0.5, 3.0, 80.0, 1e4, np.inf])
    got = np.array(marching.exp_integral(mi.Float(x)))
    with np.errstate(divide="ignore", invalid="ignore"):
        expected = np.where(x > 0, -np.expm1(-x) / x, 1.0)
    expected[np.isinf(x)] = 0.0
    assert np.allclose(got, expected, rtol=2e-6, atol=0)
    # int_0^l exp(-sigma s) ds, including l = inf (1/sigma) and sigma = 0 (l)
    sigma = mi.Float([2.0, 0.0, 1e4, 2.0])
    length = mi.Float([0.5, 0.7, 3.0, np.inf])
    got = np.array(marching.cell_integral(sigma, length))
    assert np.allclose(got, [(1 - np.exp(-1.0)) / 2, 0.7, 1e-4, 0.5], rtol=1e-6)


@pytest.mark.parametrize("spectral", [False, True])
@pytest.mark.parametrize("length", [0.3, 4.0, np.inf])
def test_cell_point_estimates_the_cell_integral(spectral, length):
    """E[weight g(s)] = int_0^l exp(-sigma s) g(s) ds for g(s) = exp(-s / 2) (which has a
    closed form), per channel; t-test, alpha 1e-3."""
    n = 1 << 16
    for sigma, spectrum in spectra_of([1.5, 1.5, 1.5] if not spectral else [0.02, 1.0, 40.0]):
        rng = np.random.default_rng(3)
        s, weight = marching.sample_cell_point(spectrum, mi.Float(length),
                                               mi.Float(rng.random(n)), spectral)
        s, weight = np.array(s), np.atleast_2d(np.array(weight))
        assert np.isfinite(weight).all() and (s >= 0).all() and (s <= length).all()
        for c, sigma_c in enumerate(sigma):
            rate = sigma_c + 0.5
            expected = (1 - np.exp(-rate * length)) / rate
            res = stats.t_test(weight[c] * np.exp(-s / 2), expected)
            assert res.p > 1e-3, f"channel {c}: {res.summary()}"
            # the one-sample MIS keeps every weight within n x the channel's cell integral
            assert weight[c].max() <= len(sigma) * (1 - np.exp(-sigma_c * length)) / sigma_c \
                * (1 + 1e-5)


def test_cell_point_extreme_channels_are_finite():
    for _, spectrum in spectra_of([0.0, 1e-4, 1e4]):
        s, weight = marching.sample_cell_point(spectrum, mi.Float([0.0, 1e-7, 5.0]),
                                               mi.Float([0.0, 0.5, 0.999999]), True)
        assert np.isfinite(np.array(weight)).all() and np.isfinite(np.array(s)).all()


@dr.syntax
def _cells(marcher, tracker, ray, t_max, u, max_cells=4096):
    """All cells ``(n, 2)`` of one march (one ray), recorded from a symbolic loop."""
    tmin, tmax = tracker.bounds(ray, mi.Float(t_max))
    state = marcher.cells.start_at(tracker, ray, tmin, tmax, mi.Float(u), mi.Bool(True))
    t = mi.Float(tmin)
    t0s = dr.zeros(mi.Float, max_cells)
    t1s = dr.zeros(mi.Float, max_cells)
    count = mi.UInt32(0)
    active = mi.Bool(tmin < tmax)
    while dr.hint(active, label="record_cells"):
        _, state = marcher.cells.next(tracker, ray, state, t, active)
        t0, t1 = mi.Float(t), mi.Float(state.t_end)
        t = dr.select(active, t1, t)
        dr.scatter(t0s, t0, count, active)
        dr.scatter(t1s, t1, count, active)
        count += 1
        active &= (t1 < tmax) & (count < max_cells)
    n = count[0]
    return np.stack([np.array(t0s)[:n], np.array(t1s)[:n]], axis=1), tmin[0], tmax[0]


@pytest.mark.parametrize("mode", marching.STEP_MODES)
def test_cells_tile_the_segment(mode):
    medium = mi.load_dict(grid(filename=SPARSE, scale=20.0))
    tracker = trackers.tracker_for(medium)
    rng = np.random.default_rng(11)
    marcher = marching.Marcher(mode, 0.05, 0.2)
    for _ in range(20):
        o = rng.uniform(-2, 2, 3)
        d = -o + rng.uniform(-0.5, 0.5, 3)
        ray = mi.Ray3f(mi.Point3f(*map(float, o)), dr.normalize(mi.Vector3f(*map(float, d))))
        cells, tmin, tmax = _cells(marcher, tracker, ray, 10.0, rng.random())
        if tmax <= tmin:
            continue
        assert cells[0, 0] == tmin and cells[-1, 1] == tmax
        assert np.array_equal(cells[1:, 0], cells[:-1, 1])     # no gaps, in order
        assert (cells[:, 1] >= cells[:, 0]).all()
        if mode == "fixed":  # (majorant mode crosses empty cells in one step)
            assert (np.diff(cells, axis=1) <= 0.05 * (1 + 1e-5)).all()


def test_majorant_mode_crosses_empty_space_in_one_step(tmp_path):
    data = np.zeros((16, 16, 16), np.float32)
    data[6:10, 6:10, 6:10] = 50.0
    np.save(tmp_path / "block.npy", data)
    tracker = trackers.tracker_for(mi.load_dict(grid(filename=str(tmp_path / "block.npy"),
                                                       scale=1.0)))
    ray = mi.Ray3f(mi.Point3f(-3, 0.01, 0.02), mi.Vector3f(1, 0, 0))
    cells, tmin, tmax = _cells(marching.Marcher("majorant", 0.05, 0.25), tracker, ray, 10.0, 0.5)
    assert cells[0, 0] == tmin and cells[-1, 1] == tmax
    # The box is [-1, 1]^3 on a 16^3 majorant grid (the march grid: the finest bounds,
    # whatever tracking's automatic resolution): cells of 0.125, 10 of them empty
    # along this ray. Each empty one is one step; the dense ones take steps of
    # step_optical_depth / sigma_maj = 0.25 / 50.
    length = np.diff(cells, axis=1)[:, 0]
    whole = np.isclose(length, 0.125, atol=1e-4)
    assert whole.sum() == 10, length
    assert (length[~whole] <= 0.005 * (1 + 1e-4)).all()
    assert np.isclose(length[~whole].sum(), 0.75, atol=1e-4)


def _smoke_segment(n):
    o = mi.Point3f(-0.5, -0.3, -0.2)
    d = dr.normalize(mi.Vector3f(1.0, 0.6, 0.5))
    return mi.Ray3f(dr.zeros(mi.Point3f, n) + o, dr.zeros(mi.Vector3f, n) + d), 1.5


@pytest.fixture(scope="module")
def smoke_medium():
    # channel 0 (red) has the largest optical depth, 0.33; outside RGB the factor is gray
    # at red's value (the marches' wavelengths are 0 nm, where an upsampled spectrum
    # means nothing, and mono would read the luminance's smaller depth)
    return mi.load_dict({"type": "grid_medium", "filename": SMOKE, "scale": 3.0,
                         "sigma_t": [1.0, 0.3, 0.08] if mi.is_rgb else 1.0,
                         "to_world": mi.ScalarTransform4f().translate([-0.5, -0.5, -0.5])})


def _marched(medium, marcher, n=1 << 18, seed=0):
    ray, length = _smoke_segment(n)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    T = marcher.transmittance(trackers.tracker_for(medium), ray, mi.Float(length), sampler,
                              mi.Bool(True))
    return np.array(T)


def test_marched_transmittance_bias_falls_with_the_step(smoke_medium):
    """Relative bias of the mean of 2^18 jittered marches through the smooth smoke
    (tau = 0.33 / 0.10 / 0.03) against the converged exp(-tau): it falls at every
    halving of the step from 0.2 to 0.0125, by at least 3x per halving on average
    (measured: 5.2e-4, 8.1e-5, 1.3e-5, 1.6e-6, 2.5e-7 in the red channel, order ~2.8)."""
    exact = np.exp(-exact_optical_depth(smoke_medium, 400000, _smoke_segment))
    steps = [0.2, 0.1, 0.05, 0.025, 0.0125]
    bias = []
    for step in steps:
        T = _marched(smoke_medium, marching.Marcher("fixed", step, 0.25))
        assert np.isfinite(T).all() and (T >= 0).all() and (T <= 1).all()
        bias.append(abs(T[0].mean() / exact[0] - 1))
    assert all(b1 < b0 for b0, b1 in zip(bias, bias[1:])), bias
    order = np.polyfit(np.log(steps), np.log(bias), 1)[0]
    assert order > np.log2(3), (order, bias)


def test_march_is_exact_in_a_constant_grid(tmp_path):
    np.save(tmp_path / "ones.npy", np.ones((4, 4, 4), np.float32))
    medium = mi.load_dict(grid(filename=str(tmp_path / "ones.npy"), scale=1.7,
                               sigma_t=[1.0, 0.5, 0.1],
                               to_world=mi.ScalarTransform4f().translate([-0.5, -0.5, -0.5])))
    ray, length = _smoke_segment(1)
    _, t0, t1 = medium.intersect_aabb(ray)
    d = float(np.clip(t1[0], 0, length) - np.clip(t0[0], 0, length))
    # the extinction at the marches' wavelengths (0 nm: spectral variants read the
    # upsampled factor there; mono its luminance); RGB: the factor itself
    mei = dr.zeros(mi.MediumInteraction3f, 1)
    sigma_t = np.array(medium.eval_sigma_t(mei)).reshape(-1)
    if mi.is_rgb:
        assert np.allclose(sigma_t, 1.7 * np.array([1.0, 0.5, 0.1]), rtol=1e-6)
    for mode in marching.STEP_MODES:
        T = np.atleast_2d(_marched(medium, marching.Marcher(mode, 0.037, 0.1), n=1024))
        assert np.allclose(T, np.exp(-sigma_t * d)[:, None], rtol=2e-5)


def test_a_new_step_size_reuses_the_kernel():
    """The step is opaque: rendering with a different step_size (and
    step_optical_depth) launches kernels with the same hashes, i.e. no recompilation."""
    scene = media_scene(grid(), sensor=camera(res=8))

    def hashes(step):
        integrator = mi.load_dict({"type": "volpath_raymarch", "step_size": step,
                                   "step_mode": "majorant", "step_optical_depth": 2 * step})
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory):
            dr.eval(mi.render(scene, integrator=integrator, spp=2))
            history = dr.kernel_history([dr.KernelType.JIT])
        return sorted(k["hash"] for k in history)

    # spectral variants: the first render of a scene traces one kernel differently
    # (whatever step it uses: 0.1 again afterwards reuses the later kernel), so warm up
    hashes(0.2)
    first = hashes(0.1)
    assert first and hashes(0.05) == first == hashes(0.0371)
