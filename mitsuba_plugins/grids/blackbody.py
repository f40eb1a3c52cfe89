r"""Blackbody emission for fire: a temperature becomes emitted radiance (issue 27).

pbrt-v4's rule (its ``nanovdb`` medium and ``BlackbodySpectrum``): Planck's law
normalised to a peak of 1,

.. math:: \hat B(\lambda, T) = B(\lambda, T) / B(\lambda_{max}(T), T),
   \qquad \lambda_{max} = b / T \ \text{(Wien)},

and 0 at or below :data:`CUTOFF` (100 K). With :math:`x = c_2 / (\lambda T)` it depends
on :math:`x` alone: :math:`\hat B = (x / x_{max})^5 (e^{x_{max}} - 1) / (e^x - 1)` with
:math:`x_{max} = c_2 / b = 4.965114...`.

* Spectral variants evaluate it at the path's wavelengths (:func:`spectrum`).
* RGB variants take the linear sRGB of the spectrum as Mitsuba's film computes it from a
  spectral render: :math:`XYZ = \int \hat B\,\bar{\mathbf{x}}\,d\lambda / \int \bar y\,
  d\lambda` over [360, 830] nm with Mitsuba's CIE 1931 tables, then Mitsuba's XYZ to
  linear sRGB matrix. So an RGB render of a fire and a spectral one agree wherever the
  colour lies in the sRGB gamut. Below about 1900 K the blackbody is more saturated than
  sRGB's red primary and the blue component is negative: it is **clamped to 0** in
  the kernel (emission is never negative); :func:`rgb_table` keeps the unclamped values.
* Monochrome variants take the luminance :math:`Y`.

The RGB/Y table covers :data:`T_MIN`..:data:`T_MAX` at :data:`TABLE_SIZE` temperatures
spaced evenly in :math:`\log T` and is interpolated linearly in :math:`\log T` (at most
1e-4 relative error against the integral, tests/grids/test_fire_and_colour_grids.py); a grid whose temperature
reaches above :data:`T_MAX` is refused when it is loaded.

This module binds no Dr.Jit type at import.
"""
from __future__ import annotations

import functools

import drjit as dr
import mitsuba as mi
import numpy as np

#: second radiation constant h c / k_B, in nm K (CODATA 2018)
C2 = 1.438776877e7
#: Wien's displacement constant, nm K
WIEN = 2.897771955e6
#: x = c2 / (lambda T) at the peak
X_MAX = C2 / WIEN
#: temperatures at or below this emit nothing (pbrt-v4's nanovdb medium)
CUTOFF = 100.0
#: range of the RGB / luminance table, kelvin
T_MIN, T_MAX = CUTOFF, 1.0e5
TABLE_SIZE = 2048
#: Mitsuba's CIE range and the integration step, nm
LAMBDA_MIN, LAMBDA_MAX, LAMBDA_STEP = 360.0, 830.0, 0.5
#: Mitsuba's XYZ -> linear sRGB (``mi.xyz_to_srgb``)
XYZ_TO_SRGB = np.array([[3.240479, -1.537150, -0.498535],
                        [-0.969256, 1.875991, 0.041556],
                        [0.055648, -0.204043, 1.057311]])


def normalised(lam_nm, temperature):
    """:math:`\\hat B(\\lambda, T)` on the host (numpy, float64); 0 at or below
    :data:`CUTOFF`."""
    lam = np.asarray(lam_nm, np.float64)
    t = np.asarray(temperature, np.float64)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        x = C2 / (lam * t)
        value = (x / X_MAX) ** 5 * np.expm1(X_MAX) / np.expm1(x)
    return np.where(t > CUTOFF, np.nan_to_num(value, nan=0.0, posinf=0.0), 0.0)


def _cmf(lam: np.ndarray) -> np.ndarray:
    """Mitsuba's CIE 1931 matching functions at ``lam`` (n, 3), through the active
    variant (its tables, not a copy)."""
    xyz = mi.cie1931_xyz(mi.Float(lam.astype(np.float32)))
    return np.stack([np.array(c, np.float64) for c in xyz], axis=-1)


@functools.lru_cache(maxsize=None)
def _tables():
    lam = np.arange(LAMBDA_MIN, LAMBDA_MAX + LAMBDA_STEP / 2, LAMBDA_STEP)
    cmf = _cmf(lam)
    temperatures = np.geomspace(T_MIN, T_MAX, TABLE_SIZE)
    spectra = normalised(lam[None, :], temperatures[:, None])            # (T, lambda)
    xyz = np.trapezoid(spectra[:, :, None] * cmf[None], lam, axis=1) / \
        np.trapezoid(cmf[:, 1], lam)
    return temperatures, xyz


def xyz_table():
    """``(temperatures, XYZ)``: the table's temperatures (kelvin) and the XYZ of
    :math:`\\hat B` at each, ``Y`` normalised so that a flat spectrum of 1 has ``Y = 1``."""
    return _tables()


def rgb_table():
    """``(temperatures, linear sRGB)`` of :func:`xyz_table`, unclamped."""
    temperatures, xyz = _tables()
    return temperatures, xyz @ XYZ_TO_SRGB.T


@functools.lru_cache(maxsize=None)
def _device_table(variant: str):
    """The table of the active variant's colour (RGB clamped at 0, or Y) as one Float
    array, ``channels`` values per temperature."""
    temperatures, xyz = _tables()
    if mi.is_monochromatic:
        table = xyz[:, 1:2]
    else:
        table = np.maximum(xyz @ XYZ_TO_SRGB.T, 0.0)
    return mi.Float(table.astype(np.float32).ravel()), table.shape[1]


def spectrum(temperature: mi.Float, wavelengths, active=True) -> mi.UnpolarizedSpectrum:
    """:math:`\\hat B` at ``temperature`` (kelvin, per lane) as the active variant's
    spectrum: at ``wavelengths`` in spectral variants, from the table otherwise (RGB
    clamped at 0, or luminance). 0 at or below :data:`CUTOFF`."""
    hot = mi.Bool(active) & (temperature > CUTOFF)
    if mi.is_spectral:
        t = dr.select(hot, temperature, 1.0)
        x = C2 / (mi.UnpolarizedSpectrum(wavelengths) * t)
        # e^x overflows to inf for x > 88: the value is then 0, as it should be
        value = dr.power(x * (1.0 / X_MAX), 5) * float(np.expm1(X_MAX)) / (dr.exp(x) - 1.0)
        return dr.select(hot, value, 0.0)
    table, channels = _device_table(mi.variant())
    # position in the table, linear in log T
    u = (dr.log(dr.clip(temperature, T_MIN, T_MAX)) - float(np.log(T_MIN))) * \
        float((TABLE_SIZE - 1) / np.log(T_MAX / T_MIN))
    i = mi.UInt32(dr.minimum(dr.floor(u), TABLE_SIZE - 2))
    f = u - mi.Float(i)
    out = []
    for c in range(channels):
        lo = dr.gather(mi.Float, table, i * channels + c, hot)
        hi = dr.gather(mi.Float, table, (i + 1) * channels + c, hot)
        out.append(dr.select(hot, dr.fma(f, hi - lo, lo), 0.0))
    return mi.UnpolarizedSpectrum(*out) if channels == 3 else mi.UnpolarizedSpectrum(out[0])
