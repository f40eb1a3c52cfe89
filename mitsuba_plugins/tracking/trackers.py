"""Trackers: the adapters through which the walks (:mod:`mitsuba_plugins.tracking.walk`) see any
heterogeneous medium (docs/architecture.md rule 2).

* :class:`Tracker` (:func:`tracker_for`): :class:`GridTracker` for a medium that offers
  :class:`~mitsuba_plugins.tracking.medium_protocol.TrackedMedium` (``grid_medium``),
  :class:`MitsubaTracker` for any other (one global majorant, checked by
  :func:`checked_majorant`);
* :func:`medium_interaction`: the interaction at a point of a ray, for lookups.

Distances are ray parameters ``t``; rays handed to a tracker have unit direction, so
``t`` is a length and the pdfs are per unit length.
"""
from __future__ import annotations


import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins import instrument
from mitsuba_plugins.grids.spectra import probe_wavelengths
from mitsuba_plugins.tracking import majorant
from mitsuba_plugins.tracking.majorant_grid import MajorantGrid
from mitsuba_plugins.tracking.medium_protocol import MediumProperties

VARIANT = mi.variant()
#: Fewest majorant cells along the grid's finest axis at which the walk crosses event-free
#: pieces in its tight loop (:attr:`Tracker.tight_loop`). Chosen on kernel times at 32x32,
#: 16 spp (``git show aa26248:benchmarks/refactor/crossing_loop.py``): with the loop forced on, the 8 grids of
#: 8 or 16 cells ran 0.88-0.99x as long as without, the 11 of 4 cells 0.95-1.02x, the 3 of
#: one cell 1.00-1.03x.
TIGHT_LOOP_CELLS = 8


def diagonal(bbox) -> float:
    """Length of a bounding box's diagonal."""
    return float(np.linalg.norm(np.array(bbox.max) - np.array(bbox.min)))


class Tracker:
    """What the walks need from one heterogeneous medium: its majorant grid, its bounds
    and its properties; one adapter per kind of medium (:class:`GridTracker` for a
    :class:`TrackedMedium`, :class:`MitsubaTracker` for any other), made by
    :func:`tracker_for`.

    ``grid`` / ``march_grid``: the bounds tracking and majorant-mode marches step by;
    ``voxels``: ``(voxels per local unit on each axis, trilinear)`` of a grid whose hot
    segments are refined, else None; ``hot``: a segment can hold more than
    ``instrument.settings.refine_optical_depth`` tentative collisions (256 by default), so a
    crossing's work is not
    bounded by construction and the walk keeps a work budget; ``diagonal``: of the
    medium's world box (None: unbounded, as Mitsuba's media say)."""
    has_emission = False
    voxels = None
    diagonal = None
    #: turns the grid's gray minorant into a lower bound of every channel
    control_scale = 1.0

    def __init__(self, medium: mi.Medium):
        self.medium = medium

    @property
    def tight_loop(self) -> bool:
        """Cross event-free pieces in the walk's tight loop
        (:func:`mitsuba_plugins.tracking.walk.walk`)? Only where the majorant grid has at least
        :data:`TIGHT_LOOP_CELLS` cells along an axis: it saves a density lookup per cell
        crossed without a tentative collision, but its loop costs ~2 ms of tracing per
        render and, on coarse grids (whose rays cross few cells), about what it saves
        (issue 29, ``git show aa26248:benchmarks/refactor/crossing_loop.py``). ``instrument.crossing_loop``
        overrides."""
        forced = instrument.settings.crossing_loop
        if forced is not None:
            return forced
        return max(self.grid.resolution) >= TIGHT_LOOP_CELLS

    def bounds(self, ray: mi.Ray3f, t_max: mi.Float):
        """``(t_in, t_out)``: the ray's stretch inside the medium's box, clipped to
        ``[0, t_max]`` (empty, ``t_in == t_out``, where it misses)."""
        hit, t0, t1 = self.medium.intersect_aabb(ray)
        t_in = dr.clip(t0, 0.0, t_max)
        t_out = dr.clip(t1, 0.0, t_max)
        return t_in, dr.select(hit & (t_in < t_out), t_out, t_in)

    def gray_sigma_t(self, ray: mi.Ray3f, t: mi.Float, active) -> mi.Float:
        """Largest channel of the extinction at ``ray(t)``."""
        return dr.max(self.sigma_t(medium_interaction(ray, t), active))


class GridTracker(Tracker):
    """A medium of ours (``PROVIDES_TRACKING``, e.g. ``grid_medium``): its majorant grid,
    refinement and emission."""

    def __init__(self, medium: mi.Medium):
        super().__init__(medium)
        self.has_emission = bool(medium.has_emission)
        self.is_chromatic = bool(medium.is_chromatic)
        self.diagonal = diagonal(medium.bbox)
        self.voxels = medium.refinement
        self.control_scale = float(medium.control_scale)
        self.grid = medium.majorant_grid
        self.march_grid = medium.march_grid
        self.hot = self.voxels is not None

    def sigma_t(self, mei: mi.MediumInteraction3f, active) -> mi.Spectrum:
        return mi.Spectrum(self.medium.eval_sigma_t(mei, active))

    def albedo(self, mei: mi.MediumInteraction3f, active) -> mi.Spectrum:
        """The single-scattering albedo (no density lookup)."""
        return mi.Spectrum(self.medium.eval_albedo(mei, active))

    def properties(self, mei: mi.MediumInteraction3f, active) -> MediumProperties:
        sigma_t = mi.Spectrum(self.medium.eval_sigma_t(mei, active))
        sigma_s = sigma_t * mi.Spectrum(self.medium.eval_albedo(mei, active))
        Le = mi.Spectrum(self.medium.get_radiance(mei, active)) if self.has_emission else \
            mi.Spectrum(0.0)
        return MediumProperties(sigma_t, sigma_s, Le)


class MitsubaTracker(Tracker):
    """Any other medium (Mitsuba's ``heterogeneous``), through Mitsuba's interface:
    ``get_scattering_coefficients`` and, where its extinction is a gridvolume, a
    majorant grid built from that grid's data (:func:`mitsuba_plugins.tracking.majorant.mitsuba_grid`,
    cached while the data stay the same); else one segment over the whole ray with the
    global majorant (a 1-cell grid whose value equals it inside and outside). The global
    majorant is read back once per render and checked (:func:`checked_majorant`); it
    bounds the grid outside its box. Chromatic as it declares."""

    def __init__(self, medium: mi.Medium, extent: float = np.inf, bbox=None):
        super().__init__(medium)
        self.is_chromatic = medium.has_spectral_extinction() and not gray_extinction(medium)
        value = checked_majorant(medium, bbox)
        cells = majorant.mitsuba_grid(medium)
        if cells is not None and cells[3] > 0:
            # a gridvolume's own data: per-cell bounds, as grid_medium has (issue 29.2)
            values, lows, grid_max, scale, to_local = cells
            m = majorant.derive(values, lows, max(grid_max, value / scale), scale, to_local,
                                auto=True, plugin=medium.class_name(),
                                source="its sigma_t grid")
            self.grid, self.march_grid = m.grid, m.march_grid
        else:
            self.grid = MajorantGrid(np.full((1, 1, 1), value, np.float32),
                                     mi.ScalarTransform4f(), value)
            self.march_grid = self.grid
        #: ``extent``: the longest stretch a ray can travel through it
        self.hot = value * extent > instrument.settings.refine_optical_depth

    def sigma_t(self, mei: mi.MediumInteraction3f, active) -> mi.Spectrum:
        _, _, sigma_t = self.medium.get_scattering_coefficients(mei, active)
        return mi.Spectrum(sigma_t)

    def properties(self, mei: mi.MediumInteraction3f, active) -> MediumProperties:
        sigma_s, _, sigma_t = self.medium.get_scattering_coefficients(mei, active)
        return MediumProperties(mi.Spectrum(sigma_t), mi.Spectrum(sigma_s), mi.Spectrum(0.0))

    def albedo(self, mei: mi.MediumInteraction3f, active) -> mi.Spectrum:
        """``sigma_s / sigma_t`` (0 where the medium is empty)."""
        props = self.properties(mei, active)
        # mi.Spectrum: in spectral variants dr.select of a spectrum and a float is a plain
        # Array4f, which a loop refuses as the throughput's new type
        return mi.Spectrum(props.sigma_s / dr.select(props.sigma_t > 0, props.sigma_t, 1.0))


def gray_extinction(medium: mi.Medium) -> bool:
    """Whether Mitsuba's ``heterogeneous`` medium has the same extinction in every channel
    although it declares spectral extinction (its default): its ``sigma_t`` is one
    channel, a float or a one-channel ``gridvolume``, which Mitsuba broadcasts to every
    channel and wavelength (its ``scale`` is always one float). Read from ``mi.traverse`` (no
    kernel), at each render: an edit cannot change a texture's channel count. Such a
    medium then takes the gray kernels (no spectral MIS over the channels) and
    ``gradient_estimator = "sm"``; Mitsuba's ``volume_optimization`` tutorial is one."""
    if medium.class_name() != "HeterogeneousMedium":
        return False
    params = mi.traverse(medium)
    if "sigma_t.data" in params.keys():
        data = params["sigma_t.data"]
        return len(data.shape) == 3 or (len(data.shape) == 4 and data.shape[3] == 1)
    return "sigma_t.value.value" in params.keys() and \
        isinstance(params["sigma_t.value.value"], mi.Float)


def tracker_for(medium: mi.Medium, extent: float = np.inf, bbox=None) -> Tracker:
    """The adapter of ``medium`` (``extent``, ``bbox``: the scene's longest stretch and
    box, for a Mitsuba medium's work budget and majorant check)."""
    if getattr(medium, "PROVIDES_TRACKING", False):
        return GridTracker(medium)
    return MitsubaTracker(medium, extent, bbox)


#: lanes (points x wavelengths) at which a Mitsuba medium's extinction is probed
PROBES = 4096
#: relative slack on a probed extinction used as a majorant
PROBE_SLACK = 1e-3
#: relative excess of a probed extinction over the majorant that is float rounding
ROUNDING = 1e-5


def checked_majorant(medium: mi.Medium, bbox=None) -> float:
    """A Mitsuba medium's global majorant, checked against its extinction at
    :data:`PROBES` points (uniform in ``bbox``, the scene's box, else the origin) and,
    in spectral variants, wavelengths over the visible range.

    Where the extinction exceeds it, the majorant is not one, and tracking with it would
    be silently biased: the largest value seen (plus :data:`PROBE_SLACK`) is used and a
    warning says so. Measured: Mitsuba's ``heterogeneous`` with a constant rgb ``sigma_t``
    (1, 0.2, 1) in ``llvm_ad_spectral`` reports 0.84 x scale (``max()`` of the upsampled
    spectrum is not its maximum, 0.9998), and ``volpath`` renders it 50 standard errors
    too bright against the equal ``homogeneous`` medium."""
    majorant = medium.get_majorant(probe_interaction(1))
    value = float(np.max(np.asarray(majorant)))
    mei = probe_interaction(PROBES)
    if bbox is not None and np.all(np.isfinite(np.array(bbox.max) - np.array(bbox.min))):
        rng = np.random.default_rng(0)
        lo, hi = np.array(bbox.min, np.float64), np.array(bbox.max, np.float64)
        p = rng.uniform(lo, hi, (PROBES, 3)).astype(np.float32)
        mei.p = mi.Point3f(*(mi.Float(p[:, i]) for i in range(3)))
    _, _, sigma_t = medium.get_scattering_coefficients(mei)
    probed = float(np.max(np.asarray(sigma_t)))
    if probed > value:
        # above it either way: tracking takes the larger; a warning only where the excess
        # is more than float rounding (``scale`` times a voxel, rounded twice: the
        # tutorial's uniform 0.002 x 40 read 0.08 against 0.0800000)
        reported, value = value, probed * (1 + PROBE_SLACK)
        if probed <= reported * (1 + ROUNDING):
            return value
        mi.Log(mi.LogLevel.Warn,
               f"mitsuba_plugins: {medium.class_name()}'s majorant {reported:g} is below its "
               f"extinction {probed:g} (seen at sampled points and wavelengths); tracking "
               f"uses {value:g} (Mitsuba's volpath with this medium is "
               "biased)")
    return value


def medium_interaction(ray: mi.Ray3f, t: mi.Float) -> mi.MediumInteraction3f:
    """A medium interaction at ``ray(t)`` (coefficient lookups, phase functions)."""
    mei = dr.zeros(mi.MediumInteraction3f)
    mei.t = t
    mei.p = ray(t)
    mei.wi = -ray.d
    mei.sh_frame = mi.Frame3f(mei.wi)
    mei.time = ray.time
    mei.wavelengths = ray.wavelengths
    return mei


def index_channel(spec, channel: mi.UInt32) -> mi.Float:
    """``spec[channel]`` per lane, for a spectrum of any channel count (3 in RGB
    variants, 4 sampled wavelengths in spectral ones, 1 in mono)."""
    value = spec[0]
    for k in range(1, len(spec)):
        value = dr.select(channel == k, spec[k], value)
    return value


def probe_interaction(width: int = 64) -> mi.MediumInteraction3f:
    """A medium interaction at the origin with :func:`probe_wavelengths`."""
    mei = dr.zeros(mi.MediumInteraction3f, width)
    if mi.is_spectral:
        mei.wavelengths = probe_wavelengths(width)
    return mei
