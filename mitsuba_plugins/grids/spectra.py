"""RGB data in every variant: how ``grid_medium``'s grids and RGB parameters become the
active variant's spectra, by Mitsuba's own rules (docs/usage.md, "Variants").

* RGB variants: values as given (1 or 3 channels).
* Monochrome variants: an RGB value becomes its luminance, as Mitsuba's ``gridvolume``
  (``luminance(interpolate_3)``) and ``rgb`` spectra do there. Luminance is linear, so
  an RGB grid is reduced to one channel when it is loaded.
* Spectral variants: an RGB voxel is upsampled as ``gridvolume`` does it: the
  coefficients of Jakob and Hanika's sigmoid-polynomial model (2019) of
  ``rgb / (2 max(rgb))`` and the scale ``2 max(rgb)``, four channels per voxel
  (Mitsuba's own conversion computes them: :func:`upsample`). A trilinear lookup
  evaluates the 8 surrounding voxels' spectra at the path's wavelengths, blends them,
  blends their scales separately and multiplies the two (``gridvolume``'s
  ``interpolate_spectral``); a nearest lookup takes one voxel's scale x spectrum. A
  constant RGB multiplier (``sigma_t``) is upsampled the same way, so a 3-channel grid
  of constant value ``k`` and a 1-channel grid of 1 times ``k`` are the same medium.

Bounds for majorants: the model's spectrum ``s(lambda) = sigmoid(c0 l^2 + c1 l + c2)`` is
monotone in the quadratic, so its extremes over [MI_CIE_MIN, MI_CIE_MAX] lie at the two
ends or at the vertex (:func:`model_range`). A blend of spectra times a blend of scales is
at most (largest spectrum) x (largest scale) of the voxels blended, so majorant cells
take the product of the two factors' cell maxima (``majorant.ProductMajorantBuilder``).

This module binds no Dr.Jit type at import (nothing is re-imported on a variant switch).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

#: Rec. 709 luminance weights (Mitsuba's ``luminance``)
LUMINANCE = np.array([0.212671, 0.715160, 0.072169], np.float32)
#: channels of an upsampled RGB voxel: three model coefficients and the scale
MODEL_CHANNELS = 4


def probe_wavelengths(width: int = 64):
    """``width`` lanes of wavelengths spread over the whole visible range [MI_CIE_MIN,
    MI_CIE_MAX] (spectral variants; None in RGB and mono ones): a spatially constant
    quantity evaluated there shows whether, and how much, it varies with the wavelength
    (``dr.zeros`` would put every lane at 0 nm)."""
    if not mi.is_spectral:
        return None
    n = dr.size_v(mi.Spectrum)
    lam = np.linspace(mi.MI_CIE_MIN, mi.MI_CIE_MAX, width * n).reshape(width, n)
    return mi.Spectrum(*[mi.Float(lam[:, k]) for k in range(n)])


def luminance(rgb: np.ndarray) -> np.ndarray:
    """``(..., 3)`` -> ``(..., 1)`` luminance, float32."""
    return (np.asarray(rgb, np.float32) @ LUMINANCE)[..., None].astype(np.float32)


def upsample(rgb: np.ndarray) -> np.ndarray:
    """``(..., 3)`` RGB -> ``(..., 4)`` (model coefficients, scale) as Mitsuba's spectral
    ``gridvolume`` stores them, computed by Mitsuba itself; a black voxel becomes all
    zeros (Mitsuba's coefficients there evaluate to ~4e-9 and :func:`model_spectrum`
    makes them exactly 0), so that zero still means empty to sparse storage."""
    rgb = np.ascontiguousarray(rgb, np.float32)
    lead = rgb.shape[:-1]
    n = int(np.prod(lead))
    if n == 0:
        return np.zeros((*lead, MODEL_CHANNELS), np.float32)
    volume = mi.load_dict({"type": "gridvolume",
                           "grid": mi.VolumeGrid(rgb.reshape(n, 1, 1, 3))})
    model = np.array(mi.traverse(volume)["data"], np.float32).reshape(n, MODEL_CHANNELS)
    model[model[:, 3] <= 0] = 0.0
    return model.reshape(*lead, MODEL_CHANNELS)


def model_spectrum(coefficients, scale, wavelengths) -> mi.UnpolarizedSpectrum:
    """The model's spectrum (without the scale) at ``wavelengths``; 0 where ``scale`` is 0
    (a black voxel)."""
    value = mi.srgb_model_eval(mi.Array3f(coefficients), wavelengths)
    return dr.select(scale > 0, mi.UnpolarizedSpectrum(value), 0.0)


def model_range(model: np.ndarray) -> tuple:
    """``(s_min, s_max)`` per voxel of ``model`` ``(..., 4)``: the extremes of its spectrum
    (scale excluded) over the wavelengths a spectral variant samples."""
    flat = np.asarray(model, np.float32).reshape(-1, MODEL_CHANNELS)
    lo, hi = float(mi.MI_CIE_MIN), float(mi.MI_CIE_MAX)
    c0, c1 = flat[:, 0].astype(np.float64), flat[:, 1].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = np.where(c0 != 0, -c1 / (2 * c0), lo)
    vertex = np.clip(np.nan_to_num(vertex, nan=lo), lo, hi).astype(np.float32)
    n = flat.shape[0]
    wavelengths = mi.Spectrum(*[mi.Float(np.full(n, lo, np.float32)),
                                mi.Float(np.full(n, hi, np.float32)),
                                mi.Float(vertex), mi.Float(vertex)][:dr.size_v(mi.Spectrum)])
    coefficients = mi.Array3f(*(mi.Float(flat[:, k]) for k in range(3)))
    values = np.array(model_spectrum(coefficients, mi.Float(flat[:, 3]), wavelengths))
    shape = np.asarray(model).shape[:-1]
    return values.min(axis=0).reshape(shape), values.max(axis=0).reshape(shape)


class GridValues:
    """What a stored voxel of a grid (density or emission) holds in the active variant,
    for a file of ``file_channels`` (1 or 3) channels: see the module docstring.

    ``channels``: stored channels (4 for upsampled RGB, 1 for RGB in mono);
    ``upsampled``: stored as the spectral model; ``converted``: stored values are not
    the file's (then the medium does not expose them for editing)."""

    def __init__(self, file_channels: int):
        self.file_channels = file_channels
        self.upsampled = bool(mi.is_spectral and file_channels == 3)
        self.gray_only = bool(mi.is_monochromatic and file_channels == 3)
        self.converted = self.upsampled or self.gray_only
        self.channels = MODEL_CHANNELS if self.upsampled else 1 if self.gray_only else \
            file_channels

    def convert(self, values: np.ndarray) -> np.ndarray:
        """File values ``(..., file_channels)`` -> stored values ``(..., channels)``."""
        if self.upsampled:
            return upsample(values)
        if self.gray_only:
            return luminance(values)
        return values

    def factors(self, stored: np.ndarray) -> tuple:
        """``(upper, lower)`` ``(..., 2)`` per voxel for :class:`ProductMajorantBuilder`
        (upsampled only): (s_max, scale) and (s_min, scale)."""
        s_min, s_max = model_range(stored)
        scale = stored[..., 3]
        return np.stack([s_max, scale], axis=-1), np.stack([s_min, scale], axis=-1)

    def spectrum(self, value, wavelengths):
        """A stored value read at one point (``value``: its channels, a sequence of
        ``Float``; a nearest lookup, or any linear blend in RGB and mono) as a spectrum."""
        if self.upsampled:
            return value[3] * model_spectrum(mi.Array3f(value[0], value[1], value[2]),
                                             value[3], wavelengths)
        if self.channels == 1:
            return mi.UnpolarizedSpectrum(value[0])
        return mi.UnpolarizedSpectrum(*value[:3])

    def blend(self, corners, f, wavelengths) -> mi.UnpolarizedSpectrum:
        """Trilinear lookup of upsampled voxels: ``corners`` the 8 stored values in the
        order x fastest, then y, then z; ``f`` the fractional position in the cell. The
        spectra and the scales are blended separately, then multiplied."""
        g = 1.0 - f
        spectrum = scale = None
        for k, value in enumerate(corners):
            w = (f.x if k & 1 else g.x) * (f.y if k & 2 else g.y) * (f.z if k & 4 else g.z)
            s = model_spectrum(mi.Array3f(value[0], value[1], value[2]), value[3],
                               wavelengths)
            spectrum = w * s if spectrum is None else dr.fma(w, s, spectrum)
            scale = w * value[3] if scale is None else dr.fma(w, value[3], scale)
        return spectrum * scale


class Multiplier:
    """A constant RGB factor (``grid_medium``'s ``sigma_t``) in the active variant: the
    three floats in RGB, their luminance in mono, the upsampled spectrum in spectral
    variants (gray stays a constant). ``upper`` / ``lower``: its largest / smallest value
    over channels or wavelengths (for majorants and controls). Its scalars are opaque."""

    def __init__(self, rgb):
        rgb = np.broadcast_to(np.asarray(rgb, np.float32).reshape(-1), (3,)).copy()
        self.rgb = rgb
        self.gray = bool(np.all(rgb == rgb[0]))
        self.model = None
        if mi.is_spectral and not self.gray:
            model = upsample(rgb)
            self.model = dr.opaque(mi.Array3f, model[:3].tolist())
            self.scale = dr.opaque(mi.Float, float(model[3]))
            s_min, s_max = model_range(model[None])
            self.upper = float(model[3] * s_max[0])
            self.lower = float(model[3] * s_min[0])
        elif mi.is_monochromatic:
            self.value = dr.opaque(mi.Float, float(luminance(rgb)[0]))
            self.upper = self.lower = float(luminance(rgb)[0])
        else:
            self.upper, self.lower = float(rgb.max()), float(rgb.min())

    def weights(self, channels: int) -> np.ndarray:
        """Per-channel weights of stored values for a gray bound (RGB: the factor per
        channel of a 3-channel grid; otherwise one weight)."""
        if channels == 3 and mi.is_rgb:
            return self.rgb
        return np.array([self.upper], np.float32)

    def spectrum(self, wavelengths, rgb_value=None):
        """The factor at ``wavelengths``; ``rgb_value`` (RGB variants): the traversed
        ``Color3f`` itself, so that a changed parameter needs no new model."""
        if self.model is not None:
            return self.scale * model_spectrum(self.model, self.scale, wavelengths)
        if mi.is_monochromatic:
            return mi.UnpolarizedSpectrum(self.value)
        if mi.is_spectral:      # gray
            return mi.UnpolarizedSpectrum(float(self.rgb[0]))
        return rgb_value
