"""The error metrics rendering papers report, beside the relative MSE that efficiency is
defined on (docs/method.md section 1).

All compare an image ``x`` with a reference ``r`` (both H x W x C, linear radiance):

- ``rel_mse``: mean over pixels and channels of (x - r)^2 / (r^2 + 0.01), minus the
  reference's own (an image independent of the reference has E[(x - r)^2] = MSE + Var(r));
- ``rel_mse_trimmed``: the same with the 0.1% of pixels of largest error left out (a pixel's
  error is its channel mean), so that a few fireflies do not decide; the reference's own
  share is subtracted over the pixels kept;
- ``mape``: mean |x - r| / (|r| + 0.01);
- ``smape``: mean 2 |x - r| / (|x| + |r| + 0.01), in [0, 2];
- ``flip``: the mean of HDR-FLIP (Andersson et al. 2021), computed by NVIDIA's own
  ``flip-evaluator`` with its defaults (67 pixels per degree, ACES, exposures from the
  reference), on the first three channels (a gray image is repeated into three);
- ``ttuv``: time to unit variance, rel. MSE x seconds: how long the estimator would need for
  a relative MSE of 1 if its error falls as 1 / time (= 1 / efficiency).

MAPE, SMAPE and FLIP are not corrected for the reference's noise (no unbiased correction
exists for them): a reference with ``FLOOR_SHARE`` of the measured rel. MSE or more also
inflates these.
"""
from __future__ import annotations

import math

import numpy as np

from mitsuba_plugins.tools import stats

#: share of pixels (largest errors) that ``rel_mse_trimmed`` leaves out
TRIM_SHARE = 1e-3
#: epsilon in the denominators of MAPE and SMAPE (image units, as REL_MSE_EPS)
APE_EPS = 1e-2
#: the metrics of an image measured against a reference, in table order
NAMES = ("rel_mse", "rel_mse_trimmed", "mape", "smape", "flip")
#: how tables and plots name them
TITLES = {"rel_mse": "rel. MSE", "rel_mse_trimmed": "rel. MSE (top 0.1% out)",
          "mape": "MAPE", "smape": "SMAPE", "flip": "FLIP"}


def pixel_rel_se(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per-pixel relative squared error, the channel mean: the summand of the rel. MSE."""
    err = (np.asarray(image, np.float64) - reference) ** 2 / (reference ** 2 + stats.REL_MSE_EPS)
    return err.mean(axis=-1)


def reference_rel_var(ref: stats.Estimate) -> np.ndarray:
    """Per-pixel relative variance of a reference (channel mean): its share of a rel. MSE."""
    return (ref.se ** 2 / (ref.mean ** 2 + stats.REL_MSE_EPS)).mean(axis=-1)


def kept_pixels(errors: np.ndarray, share: float = TRIM_SHARE) -> np.ndarray:
    """Mask of the pixels left once the ``floor(share x pixels)`` largest errors are out
    (ties broken by position, so exactly that many go)."""
    flat = errors.ravel()
    drop = int(math.floor(share * flat.size))
    keep = np.ones(flat.size, bool)
    if drop:
        keep[np.argsort(flat, kind="stable")[flat.size - drop:]] = False
    return keep.reshape(errors.shape)


def rel_mse_trimmed(image: np.ndarray, ref: stats.Estimate, share: float = TRIM_SHARE) -> float:
    errors = pixel_rel_se(image, ref.mean)
    keep = kept_pixels(errors, share)
    return float(errors[keep].mean() - reference_rel_var(ref)[keep].mean())


def mape(image: np.ndarray, reference: np.ndarray) -> float:
    x, r = np.asarray(image, np.float64), np.asarray(reference, np.float64)
    return float(np.mean(np.abs(x - r) / (np.abs(r) + APE_EPS)))


def smape(image: np.ndarray, reference: np.ndarray) -> float:
    x, r = np.asarray(image, np.float64), np.asarray(reference, np.float64)
    return float(np.mean(2 * np.abs(x - r) / (np.abs(x) + np.abs(r) + APE_EPS)))


def _flip_input(image: np.ndarray) -> np.ndarray:
    x = np.asarray(image, np.float32)
    if x.ndim == 2:
        x = x[..., None]
    x = np.repeat(x, 3, axis=2) if x.shape[2] == 1 else x[..., :3]
    # As they are: negative values (spectral variants' out-of-gamut colours) too, as
    # NVIDIA's own `flip` tool reads them from an EXR (clamping changed one by 0.7%).
    return np.ascontiguousarray(x)


def flip(image: np.ndarray, reference: np.ndarray) -> tuple:
    """``(mean, map)``: HDR-FLIP of ``image`` against ``reference`` from ``flip-evaluator``
    (the map is H x W, values in [0, 1])."""
    try:
        import flip_evaluator
    except ImportError as error:   # a dependency of the package: a broken install
        raise RuntimeError("FLIP needs the package 'flip-evaluator' (pip install "
                           "flip-evaluator), a dependency of mitsuba-plugins") from error
    error_map, mean, _ = flip_evaluator.evaluate(_flip_input(reference), _flip_input(image), "HDR",
                                                 applyMagma=False)
    return float(mean), np.asarray(error_map, np.float32).reshape(error_map.shape[:2])


def measure(image: np.ndarray, ref: stats.Estimate, floor: float) -> dict:
    """Every metric of :data:`NAMES` for ``image`` against ``ref``; ``floor`` is the
    reference's own rel. MSE (``compare.reference_floor``)."""
    return {"rel_mse": stats.rel_mse(image, ref.mean) - floor,
            "rel_mse_trimmed": rel_mse_trimmed(image, ref),
            "mape": mape(image, ref.mean), "smape": smape(image, ref.mean),
            "flip": flip(image, ref.mean)[0]}


def time_to_unit_variance(rel_mse_value: float, seconds: float) -> float:
    """rel. MSE x seconds (= 1 / efficiency); NaN where the rel. MSE is not positive."""
    return rel_mse_value * seconds if rel_mse_value > 0 else math.nan
