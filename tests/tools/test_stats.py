"""The statistics harness on synthetic data with known answers: it passes the same
expectation and it catches a 2% bias."""
import math

import numpy as np

from mitsuba_plugins.tools import stats


def synthetic(mean_img, passes, noise, rng):
    return stats.Estimate.from_passes(
        [mean_img + rng.normal(0, noise, mean_img.shape) for _ in range(passes)], 16)


def test_sidak_threshold():
    assert math.isclose(stats.sidak_z(0.05, 1), 1.959964, rel_tol=1e-5)
    assert stats.sidak_z(0.01, 10 ** 5) > stats.sidak_z(0.01, 10)


def test_same_expectation_passes_and_2pct_bias_fails():
    rng = np.random.default_rng(1)
    truth = rng.uniform(0.2, 1.0, (64, 64, 3))
    ref = synthetic(truth, 16, 0.05, rng)
    same = synthetic(truth, 8, 0.05, rng)
    biased = synthetic(truth * 0.98, 8, 0.05, rng)
    assert stats.compare(same, ref).passed
    result = stats.compare(biased, ref)
    assert not result.passed and np.all(result.mean_z < -4.5)


def test_pixel_test_is_calibrated_for_few_passes():
    """Equal expectations, 8 passes against 16 (about 11 Welch-Satterthwaite df, as in the
    integrator tests), 64x64x3 values, 20 seeds: the Welch t threshold fails a value by
    chance at the Sidak rate (1% family-wise, so almost never), while the normal threshold
    |z| > 4.8 failed 1.2e-4 of them here (Gaussian noise; render noise has heavier tails,
    and seeds of one render comparison failed up to 0.26%, see mitsuba_plugins.tools.stats)."""
    rng = np.random.default_rng(7)
    truth = rng.uniform(0.2, 1.0, (64, 64, 3))
    t_failing, z_failing = [], []
    for _ in range(20):
        a, b = synthetic(truth, 8, 0.05, rng), synthetic(truth, 16, 0.05, rng)
        result = stats.compare(a, b)
        t_failing.append(result.pixel_fail_fraction)
        z_failing.append(np.mean(np.abs(result.z) > stats.sidak_z(0.01, result.z.size)))
    assert np.mean(t_failing) < 1e-5, t_failing
    assert np.mean(z_failing) > 5e-5, z_failing      # what the t threshold corrects


def test_t_test():
    rng = np.random.default_rng(2)
    x = rng.normal(1.0, 0.1, 1000)
    assert stats.t_test(x, 1.0).p > 1e-3
    assert stats.t_test(x, 1.02).p < 1e-6


def test_rel_mse_and_efficiency():
    ref = np.ones((4, 4, 3))
    assert stats.rel_mse(ref, ref) == 0.0
    assert math.isclose(stats.rel_mse(ref * 1.1, ref), 0.01 / 1.01)
    assert math.isclose(stats.efficiency(0.01, 2.0), 50.0)


def test_block_and_image_means_take_their_errors_from_the_passes():
    """Pixels whose errors correlate (a reconstruction filter wider than a pixel, as
    Mitsuba's default Gaussian, spreads each sample over its neighbours; here, to the
    limit, one error per pass shared by every pixel, plus independent noise of 0.1) have
    block and image means that vary as one pixel does, not 1/8 or 1/32 as much as
    independent pixels would: 64 passes of 32x32, se of an 8x8 block's mean and of the
    image mean sqrt(1 + 0.01 / n) / 8, n the pixels averaged. Tolerance 35%: four standard
    deviations of a standard deviation estimated from 64 values (9%). Taken from the
    pixels as if independent (the harness before), a block's read 1/8.6 of that, and two
    such estimates of one expectation failed ``compare``'s image-mean test (z -11, now
    -0.35)."""
    rng = np.random.default_rng(11)
    passes = [rng.standard_normal() + 0.1 * rng.standard_normal((32, 32, 3)) + 1.0
              for _ in range(64)]
    e = stats.Estimate.from_passes(passes, 1)
    block = stats.block_estimate(e, stats.BLOCK).se
    assert np.all(np.abs(block / (math.sqrt(1 + 0.01 / 64) / 8) - 1) < 0.35), block
    assert np.all(np.abs(stats.image_mean_se(e) / (math.sqrt(1 + 0.01 / 1024) / 8) - 1) < 0.35)
    other = stats.Estimate.from_passes(
        [rng.standard_normal() + 0.1 * rng.standard_normal((32, 32, 3)) + 1.0
         for _ in range(64)], 1)
    assert stats.compare(e, other).passed
