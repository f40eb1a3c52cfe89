"""What our integrators ask of a medium (docs/architecture.md rule 2): the protocol
:class:`TrackedMedium` a medium of ours offers (``grid_medium``), and
:class:`MediumProperties`, what a medium is at a point."""
from __future__ import annotations

from typing import Optional, Protocol

import mitsuba as mi

from mitsuba_plugins.tracking.majorant_grid import MajorantGrid

VARIANT = mi.variant()


class TrackedMedium(Protocol):
    """The contract between a medium and our integrators' walks.

    A medium class that sets ``PROVIDES_TRACKING = True`` (``grid_medium``) promises:

    * ``majorant_grid``: a :class:`~mitsuba_plugins.tracking.majorant_grid.MajorantGrid` whose segments
      bound ``eval_sigma_t`` along any ray (tests/tracking/test_majorant.py, test_sparse_storage.py), and
      ``march_grid``, one as tight as the medium has (it may equal ``majorant_grid``),
      for marches in ``majorant`` step mode;
    * ``refinement``: ``(voxels per local unit, trilinear)`` when a segment can be hot
      (see :func:`mitsuba_plugins.tracking.walk.refined_piece`), else None;
    * ``eval_sigma_t(mei, active)``, ``eval_albedo(mei, active)`` and
      ``get_radiance(mei, active)`` (``Le``; 0 without emission), per channel;
    * ``has_emission``, ``is_chromatic`` (extinction differs between channels),
      ``bbox`` (world bounds) and ``control_scale`` (the factor that makes the grid's
      gray minorant a lower bound of every channel), plus Mitsuba's ``intersect_aabb``.

    Any other medium (Mitsuba's ``heterogeneous``) is tracked through Mitsuba's own
    interface alone: one global majorant and ``get_scattering_coefficients``.
    """
    PROVIDES_TRACKING: bool
    majorant_grid: MajorantGrid
    march_grid: MajorantGrid
    refinement: Optional[tuple]
    has_emission: bool
    is_chromatic: bool

    def eval_sigma_t(self, mei, active): ...

    def eval_albedo(self, mei, active): ...

    def get_radiance(self, mei, active): ...


class MediumProperties:
    """What a medium is at a point (pbrt-v4's ``MediumProperties``): extinction,
    scattering and emitted radiance ``Le`` (0 without emission), per channel."""
    DRJIT_STRUCT = {"sigma_t": mi.Spectrum, "sigma_s": mi.Spectrum, "Le": mi.Spectrum}

    def __init__(self, sigma_t=None, sigma_s=None, Le=None):
        self.sigma_t, self.sigma_s, self.Le = sigma_t, sigma_s, Le
