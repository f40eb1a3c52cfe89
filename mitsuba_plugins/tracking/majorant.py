"""Majorants of a medium: its per-cell bounds of extinction derived into what tracking
walks (docs/method.md section 8).

The bounds (:mod:`mitsuba_plugins.grids.bounds`, built from a grid's values slab by
slab) become a medium's :class:`Majorants` through :func:`derive` (global majorant,
:class:`~mitsuba_plugins.tracking.majorant_grid.MajorantGrid` with its DDA, the finer grid marches step
by, whether hot segments are refined), which chooses the resolution per grid and
refuses extinctions the kernels cannot hold; :func:`mitsuba_grid` derives them for
Mitsuba's ``heterogeneous``. Any medium that offers tracking
(``mitsuba_plugins.tracking.medium_protocol.TrackedMedium``) can reuse them. The
integrator decides what happens at a tentative collision; this module only bounds.
"""
from __future__ import annotations

import ast
import dataclasses
import re

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins import instrument
from mitsuba_plugins.grids.bounds import MajorantBuilder, pool
from mitsuba_plugins.params import PluginParameterError
from mitsuba_plugins.tracking.majorant_grid import MajorantGrid

VARIANT = mi.variant()

#: largest extinction (per world unit) a medium may reach, as the float32 product the
#: kernels use (value x scale x multiplier, rounded up for the majorant). Above it the
#: optical depth of a flight (extinction x distance) could overflow float32 to inf and
#: the spectral weights exp(tau_min - tau) to NaN: 1e30 leaves room for distances up
#: to 3e8 units. Any medium this dense is opaque at float32 resolution anyway.
MAX_EXTINCTION = 1e30
#: largest optical depth of one voxel (extinction x its shortest world edge). Tracking
#: cuts hot majorant cells into pieces whose number grows as the square root of this
#: (mitsuba_plugins.tracking.walk.refined_piece): at 1e8 the worst crossing stays
#: within tracking's work budget, so the answer is the unbiased one, not its roulette
#: fallback's. Transmittance through such a voxel is exp(-1e8) already.
MAX_VOXEL_OPTICAL_DEPTH = 1e8

#: default cells per axis
DEFAULT_RESOLUTION = 16


#: Resolutions per axis the automatic choice (:func:`auto_resolution`) tries.
AUTO_RESOLUTIONS = (1, 2, 4, 8, 16)
#: Cost of one DDA step (one majorant cell crossed) in units of one density lookup (a
#: tentative collision). Fit by hand on the 8 grids of benchmarks/dense.py's family (issue
#: 16), so in-sample: with 1, the resolution chosen had the lowest time per sample of 1-32
#: cells per axis on 7 of them and was within 1% on the eighth, where a fixed 16 (the
#: former default) was up to 1.32x slower (``benchmarks/results/dense_majorant.md``).
CELL_COST = 1.0


def auto_resolution(values: np.ndarray, scale: float, axis_lengths,
                    candidates=AUTO_RESOLUTIONS, cell_cost: float = CELL_COST) -> tuple:
    """The coarsening ``(rz, ry, rx)`` of the cell bounds ``values`` (before ``scale``) that
    minimises the expected work per unit of ray length through the box: density lookups
    (mean majorant x scale x the world length of a local axis, ``axis_lengths``) plus
    ``cell_cost`` per cell crossed (cells per axis). Thin media get few cells (the DDA's
    steps would outnumber the lookups they save), dense heterogeneous ones fine cells."""
    length = float(np.mean(axis_lengths))
    best, best_cost = tuple(values.shape), np.inf
    for n in candidates:
        shape = tuple(min(n, r) for r in values.shape)
        with np.errstate(over="ignore", invalid="ignore"):
            cost = float(np.mean(pool(values, shape))) * scale * length + \
                cell_cost * float(np.mean(shape))
        if cost < best_cost:      # ties keep the coarser; NaN never wins
            best, best_cost = shape, cost
    return best


@dataclasses.dataclass
class Majorants:
    """What tracking needs from a medium's bounds (see :func:`derive`)."""
    global_majorant: object          # opaque mi.Float: the bound everywhere
    grid: MajorantGrid               # per-cell bounds and minorants, with the DDA
    march_grid: MajorantGrid         # the finest bounds, for majorant-mode marches
    refinement: tuple | None         # (voxels per local unit, trilinear) if cells can be hot
    cells: tuple                     # the cells' shape (Z, Y, X) tracking walks


def world_linear(to_local) -> np.ndarray:
    """The 3x3 linear part of a grid's local -> world map (columns: the world images of
    the local unit axes)."""
    return np.array(to_local.inverse().matrix, dtype=np.float64)[:3, :3]


def derive(values: np.ndarray, lows: np.ndarray, grid_max: float, scale: float, to_local,
           auto: bool, voxels=None, shape=None, plugin: str = "medium",
           source: str = "the medium", cells=None) -> Majorants:
    """A medium's :class:`Majorants` from cell bounds ``values`` / ``lows`` and the
    largest value ``grid_max`` (all before ``scale``), over the unit cube of
    ``to_local``'s frame.

    ``auto``: coarsen the cells to :func:`auto_resolution`'s choice (the march grid keeps
    the fine bounds). ``voxels``: ``(voxels per local unit, trilinear)`` of a voxel grid
    (None: lookups are not ours, nothing to refine); ``shape``: its ``(Z, Y, X, ...)``,
    for the voxel optical-depth check. Extinctions that float32 cannot hold are refused
    naming ``plugin``'s parameter ``scale`` and ``source``.

    ``cells``: the cells' shape to keep (a former :attr:`Majorants.cells`) instead of
    ``auto``'s choice: after an edit of the values (an optimiser's step) the kernels then
    walk the same grid and are not compiled again (issue 48); the bounds stay bounds."""
    scale32 = np.float32(scale)
    fine = None   # the bounds as built, when tracking gets coarser ones
    if (auto or cells is not None) and to_local is not None and values.size > 1:
        coarse = tuple(cells) if cells is not None else auto_resolution(
            values, float(scale32), np.linalg.norm(world_linear(to_local), axis=0))
        if coarse != values.shape:
            fine = values
            values, lows = pool(values, coarse), pool(lows, coarse, np.min)
    with np.errstate(over="ignore", invalid="ignore"):
        majorant, cells = scale32 * np.float32(grid_max), values * scale32
    _check_extinction(scale, float(grid_max), majorant, cells, plugin, source)
    if shape is not None:
        _check_voxel_optical_depth(float(majorant), to_local, shape, plugin, source)
    hot = voxels is not None and _has_hot_cells(cells, to_local)
    grid = MajorantGrid(cells, to_local, float(majorant), minorants=lows * scale32)
    return Majorants(
        global_majorant=dr.opaque(mi.Float, float(majorant)), grid=grid,
        # the automatic coarsening weighs lookups against tracking's DDA steps; a march
        # takes step_optical_depth / sigma_maj steps per unit length: the finest bounds
        march_grid=grid if fine is None else MajorantGrid(fine * scale32, to_local,
                                                          float(majorant)),
        refinement=voxels if hot else None, cells=tuple(values.shape))


def _has_hot_cells(cells: np.ndarray, to_local) -> bool:
    """Can a ray cross a majorant cell with optical depth (bound x length) above
    ``instrument.settings.refine_optical_depth``? The longest segment in a cell is its longest
    diagonal."""
    if not cells.size:
        return False
    linear = world_linear(to_local)
    rz, ry, rx = cells.shape
    diagonals = [linear @ (np.array([sx, sy, 1.0]) / (rx, ry, rz))
                 for sx in (-1, 1) for sy in (-1, 1)]
    longest = max(float(np.linalg.norm(d)) for d in diagonals)
    return float(np.max(cells)) * longest > instrument.settings.refine_optical_depth


def _check_voxel_optical_depth(majorant: float, to_local, shape, plugin, source) -> None:
    z, y, x = shape[:3]
    edge = float(np.min(np.linalg.norm(world_linear(to_local), axis=0) / np.array([x, y, z])))
    depth = majorant * edge
    if depth <= MAX_VOXEL_OPTICAL_DEPTH:
        return
    raise PluginParameterError(
        f"{plugin}: the densest voxel of {source} has optical depth {depth:.3g} (extinction "
        f"{majorant:.3g} x shortest voxel edge {edge:.3g}); allowed: at most "
        f"{MAX_VOXEL_OPTICAL_DEPTH:g}: lower parameter 'scale' (any voxel of optical depth "
        "above ~50 is opaque)")


def _check_extinction(scale: float, grid_max: float, majorant, cells, plugin, source) -> None:
    """The extinction as the kernels compute it, in float32: finite and at most
    :data:`MAX_EXTINCTION`, the majorants included (checking the doubles would let
    scale = 1e39, inf in float32, through)."""
    top = max(float(majorant), float(np.max(cells)) if cells.size else 0.0)
    if np.isfinite(np.float32(scale)) and np.isfinite(top) and top <= MAX_EXTINCTION:
        return
    raise PluginParameterError(
        f"{plugin}: extinction too large: parameter 'scale' = {scale:g} times the largest "
        f"density of {source} (times sigma_t), {grid_max:g}, gives a majorant of {top:g} "
        f"in float32; allowed: a product of at most {MAX_EXTINCTION:g} per unit length")


# -- Mitsuba's own grid media -------------------------------------------------------------
_MATRIX = re.compile(r"sigma_t = GridVolume\[\s*to_local = Transform\[\s*matrix=(\[\[.*?\]\])",
                     re.S)
#: cell bounds of Mitsuba grid media, by their data's fingerprint (see :func:`mitsuba_grid`)
_MITSUBA_CACHE: dict = {}


def _share_ends(cells: np.ndarray, op) -> None:
    """In place: the first and last cell of every axis both take ``op`` of the two."""
    for axis in range(cells.ndim):
        view = np.moveaxis(cells, axis, 0)
        view[0] = view[-1] = op(view[0], view[-1])


def mitsuba_grid(medium: mi.Medium):
    """Majorants of Mitsuba's ``heterogeneous`` medium from its ``sigma_t`` gridvolume's
    data, so that an existing scene is tracked cell by cell as ``grid_medium`` is (issue
    29.2); None where that cannot be done exactly (no grid, or several channels outside
    RGB variants, where the spectral upsampling of a voxel is not bounded by its largest
    channel), and the caller keeps one global majorant.

    The data and ``scale`` come from ``mi.traverse``; the grid's placement, which the
    Python binding does not expose, from the medium's description (``to_local``). Cell
    bounds assume clamped lookups at the box's faces; Mitsuba's ``repeat`` wrap mode
    blends the first voxel of an axis with the last, so each axis's first and last cell
    take the larger of their two bounds. Bounds are rebuilt only when the data's
    fingerprint (shape, sum, maximum, scale) changes."""
    if medium.class_name() != "HeterogeneousMedium":
        return None
    params = mi.traverse(medium)
    if "sigma_t.data" not in params.keys():
        return None
    data, scale = params["sigma_t.data"], float(params["scale"])
    channels = data.shape[3] if len(data.shape) == 4 else 1
    if channels > 1 and "rgb" not in mi.variant():
        return None
    match = _MATRIX.search(str(medium))
    if match is None:
        return None
    to_local = mi.ScalarTransform4f(np.array(ast.literal_eval(match.group(1)),
                                             dtype=np.float64))
    flat = data.array
    key = (tuple(data.shape), scale, dr.sum(flat)[0], dr.max(flat)[0],
           match.group(1))
    if key not in _MITSUBA_CACHE:
        values = np.asarray(data, dtype=np.float32).reshape(
            tuple(data.shape[:3]) + (channels,))
        if not np.all(np.isfinite(values)) or np.any(values < 0):
            return None
        shape = values.shape
        builder = MajorantBuilder(shape, (min(DEFAULT_RESOLUTION, shape[2]),
                                          min(DEFAULT_RESOLUTION, shape[1]),
                                          min(DEFAULT_RESOLUTION, shape[0]))).add_all(values)
        cells, lows = builder.finish(), builder.finish_min()
        _share_ends(cells, np.maximum)      # repeat wrap mode: the edges blend
        _share_ends(lows, np.minimum)
        if len(_MITSUBA_CACHE) >= 8:
            _MITSUBA_CACHE.pop(next(iter(_MITSUBA_CACHE)))
        _MITSUBA_CACHE[key] = (cells, lows, builder.max, scale, to_local)
    return _MITSUBA_CACHE[key]
