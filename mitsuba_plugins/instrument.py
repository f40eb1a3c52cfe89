"""Instrumentation and switches for benchmarks and tests: one object, read at trace time.

Kernels traced while a setting is changed obey it; by default nothing is counted and no
counting code is traced. Tools change the settings only through the context managers,
which restore them on exit (no module global of the core is rebound from outside):

* :func:`counting`: counts of events in the kernels (:data:`SLOTS`), read after a render;
* :func:`only_terms`: the terms of the volumetric estimator added to ``L``
  (:data:`TERMS`: light found by phase/BSDF sampling, and emitter sampling), to measure
  the variance of each;
* :func:`refinement`: the optical depth above which a majorant segment is *hot* and cut
  into refined pieces (:data:`REFINE_OPTICAL_DEPTH` by default; ``inf``: never, as with
  Mitsuba's one global majorant; tiny: everywhere). Read when a grid medium is loaded
  and when a kernel is traced;
* :func:`crossing_loop`: force the walk's tight loop over event-free pieces on or off
  (None: each medium's own choice, :attr:`mitsuba_plugins.tracking.trackers.Tracker.tight_loop`).
"""
from __future__ import annotations

import contextlib

#: Events counted, by name: null collisions of free flights, every tentative collision of
#: shadow rays, real scattering vertices in media, real surface vertices, ray
#: intersections (path and shadow rays), shadow rays, every tentative collision of
#: free flights (each a density lookup), and majorant segments fetched by tracking (DDA
#: steps, one per majorant cell crossed).
SLOTS = ("flight_null", "shadow_tentative", "medium_vertices", "surface_vertices",
         "intersections", "shadow_rays", "flight_tentative", "segments")
#: Terms of the volumetric estimator: emitters found by phase/BSDF sampling (MIS-weighted)
#: and emitter sampling (next-event estimation).
TERMS = ("emission", "nee")
#: A majorant segment of optical depth (sigma_maj x length) above this is *hot*: walked
#: in pieces with tighter bounds (:func:`mitsuba_plugins.tracking.walk.refined_piece`); below it,
#: plain tracking takes at most this many tentative collisions per segment on average,
#: which is cheaper than pieces (each costs a lookup): at 16 the benchmark's max/mean-100
#: grid (cells of optical depth 43) was refined and its time per sample rose 1.37x over
#: max/mean 30 with the same collision counts. Our scenes' segments stay below 7
#: (sparse.xml); the hard cases of 1e4 (optical depth ~2000) and beyond are refined.
REFINE_OPTICAL_DEPTH = 256.0


class Settings:
    """The current settings (see the module docstring)."""

    def __init__(self):
        self.counters = None                      # mi.UInt32 per slot while counting
        self.terms = TERMS
        self.refine_optical_depth = REFINE_OPTICAL_DEPTH
        self.crossing_loop = None                 # None: per medium; True / False: forced


#: the one instance the core reads
settings = Settings()


def count(slot: str, active) -> None:
    """In a kernel: add 1 to counter ``slot`` on the ``active`` lanes (nothing traced
    unless :func:`counting`)."""
    if settings.counters is not None:
        import drjit as dr
        import mitsuba as mi
        dr.scatter_add(settings.counters, mi.UInt32(1), mi.UInt32(SLOTS.index(slot)), active)


class Counts:
    """What :func:`counting` counted: ``counts[name]`` (a float; evaluates the kernels)."""

    def __init__(self, counters):
        self.counters = counters

    def __getitem__(self, name: str) -> float:
        import numpy as np
        return float(np.asarray(self.counters)[SLOTS.index(name)])

    def as_dict(self) -> dict:
        return {name: self[name] for name in SLOTS}


@contextlib.contextmanager
def counting():
    """Count events in the kernels traced inside the block (fresh counters, zero)."""
    import drjit as dr
    import mitsuba as mi
    previous = settings.counters
    settings.counters = dr.zeros(mi.UInt32, len(SLOTS))
    dr.make_opaque(settings.counters)
    try:
        yield Counts(settings.counters)
    finally:
        settings.counters = previous


@contextlib.contextmanager
def only_terms(*terms: str):
    """Add only these terms of the volumetric estimator (:data:`TERMS`) to ``L``."""
    unknown = set(terms) - set(TERMS)
    if unknown:
        raise ValueError(f"unknown terms {sorted(unknown)}; allowed: {', '.join(TERMS)}")
    previous, settings.terms = settings.terms, tuple(terms)
    try:
        yield
    finally:
        settings.terms = previous


@contextlib.contextmanager
def refinement(optical_depth: float):
    """Hot majorant segments are those of optical depth above ``optical_depth``."""
    previous, settings.refine_optical_depth = settings.refine_optical_depth, optical_depth
    try:
        yield
    finally:
        settings.refine_optical_depth = previous


@contextlib.contextmanager
def crossing_loop(mode):
    """Kernels traced inside the block cross event-free pieces in the walk's tight loop
    (True), never (False), or as each medium chooses (None)."""
    if mode not in (None, True, False):
        raise ValueError(f"crossing_loop: {mode!r}; allowed: None, True, False")
    previous, settings.crossing_loop = settings.crossing_loop, mode
    try:
        yield
    finally:
        settings.crossing_loop = previous
