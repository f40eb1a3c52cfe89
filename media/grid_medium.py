"""Heterogeneous grid medium with a majorant grid; a drop-in for Mitsuba's ``heterogeneous``."""
from __future__ import annotations

import re

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins import bricks, gridio
from mitsuba_plugins.majorant import (DEFAULT_RESOLUTION, MARGIN, MajorantBuilder, MajorantGrid,
                                      auto_resolution, pool, ray_box, resolution_for,
                                      voxel_ranges)
from mitsuba_plugins.params import Params, PluginParameterError

VARIANT = mi.variant()

#: elements moved to device memory per scatter while loading (bounds the extra memory)
UPLOAD_CHUNK = 1 << 18
#: margin (local units) of majorant cells when a nested volume's transform is read
#: back from its printed 6-digit matrix
PARSED_TRANSFORM_MARGIN = 2e-3
INTERPOLATIONS = {"trilinear": dr.FilterMode.Linear, "nearest": dr.FilterMode.Nearest}
#: largest extinction (per world unit) a grid may reach, as the float32 product the
#: kernels use (value x scale x sigma_t, rounded up for the majorant). Above it the
#: optical depth of a flight (extinction x distance) could overflow float32 to inf and
#: the spectral weights exp(tau_min - tau) to NaN: 1e30 leaves room for distances up
#: to 3e8 units. Any medium this dense is opaque at float32 resolution anyway.
MAX_EXTINCTION = 1e30
#: largest optical depth of one voxel (extinction x its shortest world edge). Tracking
#: cuts hot majorant cells into pieces whose number grows as the square root of this
#: (mitsuba_plugins.walk.refined_piece): at 1e8 the worst crossing stays
#: within tracking's work budget, so the answer is the unbiased one, not its roulette
#: fallback's. Transmittance through such a voxel is exp(-1e8) already.
MAX_VOXEL_OPTICAL_DEPTH = 1e8
#: smallest |det| of to_world's linear part relative to its largest entry cubed
SINGULAR_TOLERANCE = 1e-12
STORAGES = ("dense", "sparse", "auto")
#: ``storage = auto`` keeps bricks when they take at most this fraction of the dense bytes
AUTO_SPARSE_FRACTION = 0.5
#: sparse grids up to this many voxels get voxel-exact majorants, as dense ones (built
#: from a dense copy, at most 64 MiB): at 48^3 the brick bounds (6^3 cells) made
#: volpath_delta 1.43x slower on scenes/sparse.xml than the dense grid's 16^3
EXACT_MAJORANT_VOXELS = 256 ** 3


class GridMedium(mi.Medium):
    r"""
    .. _medium-grid_medium:

    Heterogeneous grid medium (:monosp:`grid_medium`)
    -------------------------------------------------

    .. pluginparameters::

     * - filename
       - |string|
       - Density grid: Mitsuba's binary ``.vol`` (1 or 3 channels), a float ``.npy`` of
         shape ``(Z, Y, X)`` or ``(Z, Y, X, C)``, or an OpenVDB ``.vdb`` (float, half or
         vec3s grid; read through Debian's ``python3-openvdb``, see
         :mod:`mitsuba_plugins.vdb`). Without it, ``sigma_t`` is the extinction itself,
         as in ``heterogeneous``.
     * - grid
       - |string|
       - Which grid of a ``.vdb`` file gives the density; a missing name is an error
         listing the file's grids. (Default: ``density``)
     * - sigma_t
       - |float|, |rgb| or |volume|
       - With ``filename``: a per-channel multiplier of the density (chromatic extinction),
         >= 0. Without: the extinction (a nested ``gridvolume`` or a constant).
         (Default: 1)
     * - scale
       - |float|
       - Multiplies the extinction, >= 0. (Default: 1)
     * - albedo
       - |float|, |rgb| or |volume|
       - Single-scattering albedo, in [0, 1]. (Default: 0.75)
     * - emission
       - |float|, |rgb| or |volume|
       - Emitted radiance :math:`L_e` (>= 0), for integrators that support emissive media;
         the emitted power per unit length is :math:`\sigma_a L_e`. Mitsuba's built-in
         integrators ignore it. (Default: none)
     * - emission_grid
       - |string|
       - A grid of the same ``.vdb`` file (float or vec3s, e.g. ``temperature`` or
         ``flames``, values >= 0) that multiplies ``emission`` (which defaults to 1 when
         this is given), placed by its own index-to-world transform (then ``to_world``),
         interpolated as the density, stored in bricks. (Default: none)
     * - interpolation
       - |string|
       - ``trilinear`` or ``nearest`` lookups of the ``filename`` grid. (Default: trilinear)
     * - to_world
       - |transform|
       - Places the ``filename`` grid's unit cube in the world; for a ``.vdb``, applies on
         top of the file's own index-to-world transform (voxel ``(i, j, k)`` at the
         transform of ``(i, j, k)``, background 0 outside the active voxels).
         (Default: identity)
     * - use_grid_bbox
       - |bool|
       - Place the ``.vol`` grid in its header's bounding box (then ``to_world``), as
         ``gridvolume`` does. (Default: false)
     * - storage
       - |string|
       - How a ``filename`` grid is held: ``dense`` (one 3D texture of the whole box),
         ``sparse`` (8^3-voxel bricks that hold a non-zero value, plus their apron, in
         one pool with an indirection grid: memory follows the occupied bricks), or
         ``auto`` (sparse when that takes at most half the dense bytes). Loading streams
         the file in slabs either way. (Default: ``auto`` for ``.vdb``, else ``dense``)
     * - majorant_resolution
       - |int|
       - Cells per axis of the majorant grid, in [1, 1024] (capped at the grid's
         resolution; for a sparse grid above 256^3 voxels at its bricks per axis, the
         bounds then being the bricks' extrema). (Default: chosen per grid among 1, 2, 4,
         8 and 16 by the expected lookups plus cells crossed per unit length: few cells
         for a thin medium, 16 for a dense heterogeneous one)
     * - has_spectral_extinction
       - |bool|
       - Tell integrators the extinction differs between channels. (Default: true when it
         can: a 3-channel grid or a non-gray multiplier)
     * - sample_emitters
       - |bool|
       - As Mitsuba's media: cast shadow rays from inside the medium. (Default: true)
     * - (nested)
       - |phase|
       - Phase function. (Default: isotropic)

    Extinction :math:`\sigma_t(x) = s\,k\,\rho(T^{-1}x)` with scale :math:`s`, multiplier
    :math:`k` and the interpolated grid :math:`\rho` on the unit cube
    (``gridvolume``'s convention: voxel centres at :math:`(i + 1/2)/N`, clamped beyond),
    :math:`\sigma_s = \alpha\sigma_t`. ``get_majorant`` returns one gray global majorant
    :math:`\max_c \max_x \sigma_{t,c}(x)`: Mitsuba's ``volpath`` samples distances with
    it and stays unbiased with chromatic extinction. :attr:`majorant_grid` holds
    per-cell bounds and a DDA (:mod:`mitsuba_plugins.majorant`) for our integrators.
    With a nested ``sigma_t`` volume and no ``filename`` it renders exactly what
    ``heterogeneous`` renders.

    The ``filename`` grid is streamed from disk in slabs into one device buffer: peak
    memory is about one copy of the raw grid (``gridvolume`` holds two), or, stored
    sparse, about the brick pool (:mod:`mitsuba_plugins.bricks`).

    ``mi.traverse`` exposes ``scale``, ``sigma_t`` (the multiplier), ``albedo``,
    ``emission`` and the phase function's parameters; with dense storage also ``data``,
    the grid tensor (same shape; the majorants are rebuilt on update). Sparse storage
    does not expose its pool: changing voxel values would change which bricks exist.
    """

    #: implements mitsuba_plugins.contract.TrackedMedium (majorant_grid, refinement,
    #: eval_sigma_t, eval_albedo, get_radiance, has_emission, is_chromatic, bbox)
    PROVIDES_TRACKING = True

    ALLOWED = ("filename", "grid", "sigma_t", "scale", "albedo", "emission", "interpolation",
               "to_world", "use_grid_bbox", "majorant_resolution", "has_spectral_extinction",
               "sample_emitters", "storage", "emission_grid")
    FILE_ONLY = ("interpolation", "to_world", "use_grid_bbox", "grid", "storage",
                 "emission_grid")

    def __init__(self, props: mi.Properties):
        if not mi.is_rgb:
            raise PluginParameterError(
                f"grid_medium: variant '{mi.variant()}' is not supported; use an RGB variant "
                "(llvm_ad_rgb or cuda_ad_rgb): extinction, albedo and emission are RGB")
        super().__init__(props)
        p = Params(props, "grid_medium", self.ALLOWED, objects=(mi.PhaseFunction,))
        scale = p.float("scale", 1.0, lo=0.0)
        with np.errstate(over="ignore"):   # an overflow to inf is what is refused here
            scale_f32 = np.float32(scale)
        if not np.isfinite(scale_f32):
            raise PluginParameterError(
                f"grid_medium: parameter 'scale' = {scale:g} is invalid; allowed: a finite "
                "number >= 0 that float32 holds (at most 3.4e38)")
        self.albedo = _volume(p, "albedo", 0.75, hi=1.0)
        self.emission = _volume(p, "emission", None) if p.has("emission") else None
        self.emission_grid = None   # (SparseGrid, to_local) of ``emission_grid``
        self.cells = p.int("majorant_resolution", DEFAULT_RESOLUTION, lo=1, hi=1024)
        #: not given: coarsen the bounds per grid (majorant.auto_resolution)
        self.auto_cells = not p.has("majorant_resolution")
        self.filename = None
        self.sparse = None  # SparseGrid when the filename grid is stored in bricks
        self.volume = None  # nested sigma_t volume (no filename)
        if p.has("filename"):
            self.filename = str(mi.file_resolver().resolve(p.props["filename"]))
            factor = _color(p, "sigma_t", 1.0)
            self.interpolation = p.choice("interpolation", "trilinear", tuple(INTERPOLATIONS))
            to_world = _transform(p.props["to_world"]) if p.has("to_world") else \
                mi.ScalarTransform4f()
            if p.has("to_world"):
                _check_invertible(p.props["to_world"])
            self.grid_name = p.props["grid"] if p.has("grid") else "density"
            for name in ("grid", "emission_grid"):
                if p.has(name) and not self.filename.lower().endswith(".vdb"):
                    raise PluginParameterError(
                        f"grid_medium: parameter '{name}' selects a grid of a .vdb file; "
                        f"'{self.filename}' is not one")
            if p.has("emission_grid"):
                if self.emission is None:
                    self.emission = _volume(p, "emission", 1.0)
                self.emission_grid = _load_emission_grid(self.filename,
                                                         p.props["emission_grid"], to_world)
            is_vdb = self.filename.lower().endswith(".vdb")
            self.storage = p.choice("storage", "auto" if is_vdb else "dense", STORAGES)
            data, to_local, bbox, builder = self._load(self.filename, to_world,
                                                       p.bool("use_grid_bbox", False),
                                                       factor)
            if data is not None:
                self.data = data
                self.texture = mi.Texture3f(data, use_accel=True, migrate=True,
                                            filter_mode=INTERPOLATIONS[self.interpolation],
                                            wrap_mode=dr.WrapMode.Clamp)
            self.to_local = to_local
            self.bbox = bbox
            self.sigma_t_factor = mi.Color3f(factor)
            self.channels = self.shape[3]
            z, y, x = self.shape[:3]
            # voxels per local unit on each axis, and whether lookups are trilinear
            self._voxels = (mi.Vector3f(x, y, z), self.interpolation == "trilinear")
        else:
            given = [name for name in self.FILE_ONLY if p.has(name)]
            if given:
                raise PluginParameterError(
                    f"grid_medium: parameter '{given[0]}' applies to a 'filename' grid; with "
                    "a nested sigma_t volume set it on the volume (e.g. gridvolume's "
                    "'filter_type', 'to_world', 'use_grid_bbox')")
            self.volume = _volume(p, "sigma_t", 1.0)
            self.bbox = self.volume.bbox()
            self.channels = self.volume.channel_count()
            self.sigma_t_factor = mi.Color3f(1.0)
            self._voxels = None  # a nested volume's lookups are Mitsuba's own
            builder = None
        self.scale = mi.Float(scale)
        chromatic = self.channels == 3 or len(set(_floats(self.sigma_t_factor))) > 1
        self.m_has_spectral_extinction = p.bool("has_spectral_extinction", chromatic)
        self.m_is_homogeneous = False
        self.is_chromatic = chromatic
        self._update_majorants(builder)

    # -- loading ---------------------------------------------------------------------
    def _load(self, path, to_world, use_grid_bbox, factor):
        """Stream ``path`` into a device tensor, validating every slab; nothing is kept
        if any check fails."""
        header = gridio.read_header(path, self.grid_name)
        if header.index_to_world is not None:
            to_world = _vdb_to_world(header, to_world)
        if use_grid_bbox and header.bbox is None:
            raise PluginParameterError(
                f"grid_medium: parameter 'use_grid_bbox' needs a .vol file (with a bounding "
                f"box in its header); '{path}' has none")
        to_local = to_world.inverse()
        if use_grid_bbox:
            lo, hi = (np.asarray(v, dtype=np.float32) for v in header.bbox)
            to_local = mi.ScalarTransform4f().scale(1.0 / (hi - lo)).translate(-lo) @ to_local
        self.shape = header.shape
        if self.storage != "dense":
            return self._load_bricks(header, to_local, factor)
        builder = MajorantBuilder(header.shape, resolution_for(header.shape, self.cells),
                                  _weights(factor, header.channels))
        flat = dr.zeros(mi.Float, header.size)
        slab_elems = int(np.prod(header.shape[1:]))
        for z0, slab in gridio.iter_slabs(header):
            gridio.check_values(path, "density", slab)
            builder.add(z0, slab)
            values = slab.reshape(-1)
            for start in range(0, values.size, UPLOAD_CHUNK):
                chunk = values[start:start + UPLOAD_CHUNK]
                index = dr.arange(mi.UInt32, z0 * slab_elems + start,
                                  z0 * slab_elems + start + chunk.size)
                dr.scatter(flat, mi.Float(chunk), index)
                dr.eval(flat)
        data = mi.TensorXf(flat, shape=header.shape)
        return data, to_local, _world_bbox(to_local), builder

    def _load_bricks(self, header, to_local, factor):
        """Stream the grid into bricks (:mod:`mitsuba_plugins.bricks`); ``storage =
        auto`` falls back to dense storage when the bricks save less than half."""
        from mitsuba_plugins.sparse import SparseGrid
        builder = _read_bricks(header, "density")
        index = builder.index
        maxima, minima = builder.extrema()
        sparse_bytes = 4 * (index.size + builder.stored * bricks.SIDE ** 3 * header.channels)
        if self.storage == "auto" and sparse_bytes > AUTO_SPARSE_FRACTION * 4 * header.size:
            self.storage = "dense"
            _, pool, _, _ = builder.finish()
            data = bricks.densify(index, pool, header.shape)
            del pool
            majorants = MajorantBuilder(header.shape, resolution_for(header.shape, self.cells),
                                        _weights(factor, header.channels)).add_all(data)
            return mi.TensorXf(data), to_local, _world_bbox(to_local), majorants
        self.storage = "sparse"
        self.sparse = SparseGrid(header.shape, index, builder.pool_chunks(), builder.stored)
        self.brick_extrema = (maxima, minima, index)
        return None, to_local, _world_bbox(to_local), None

    def _brick_majorants(self):
        """Cell bounds of sparse storage from the bricks' extrema (gray, weighted by the
        sigma_t multiplier), and the largest value (the global bound before scale)."""
        maxima, minima, index = self.brick_extrema
        # Default 16 as for dense storage: on the 1024^3 cloud of
        # benchmarks/sparse_scale.py, 64 cells per axis made volpath_delta 1.4x slower
        # (more DDA steps, no fewer collisions), 32 1.15x; at most one cell per brick.
        rz, ry, rx = (min(self.cells, c) for c in index.shape)
        z, y, x = self.shape[:3]
        ranges = (voxel_ranges(z, rz), voxel_ranges(y, ry), voxel_ranges(x, rx))
        weights = _weights(_floats(self.sigma_t_factor), self.channels)
        values, lows = bricks.cell_bounds(maxima, minima, index, self.shape, ranges, weights)
        from mitsuba_plugins.majorant import ROUNDING
        grid_max = np.float32((maxima * weights).max())
        return ((values * np.float32(1 + ROUNDING)).astype(np.float32),
                (lows * np.float32(1 - ROUNDING)).astype(np.float32), grid_max)

    def _update_majorants(self, builder=None):
        """(Re)derive the global majorant and the majorant grid from the current data."""
        to_local = self.to_local if self.volume is None else None
        if builder is None:
            builder, to_local = self._majorant_builder()
        if builder == "bricks":
            values, lows, grid_max = self._brick_majorants()
        elif builder is None:
            # A constant (or procedural) volume: one cell over its bounding box.
            grid_max = np.float32(self.volume.max())
            values = lows = np.full((1, 1, 1), grid_max, np.float32)
        else:
            values, lows = builder.finish(), builder.finish_min()
            # heterogeneous's majorant is scale * volume.max(); keep it bit for bit.
            grid_max = np.float32(self.volume.max() if self.volume is not None else builder.max)
        scale = np.float32(_floats(self.scale)[0])
        fine = None   # the bounds as built, when tracking gets coarser ones
        if self.auto_cells and to_local is not None and values.size > 1:
            shape = auto_resolution(values, float(scale),
                                    np.linalg.norm(_world_linear(to_local), axis=0))
            if shape != values.shape:
                fine = values
                values, lows = pool(values, shape), pool(lows, shape, np.min)
        with np.errstate(over="ignore", invalid="ignore"):
            majorant, cells = scale * grid_max, values * scale
        self._check_extinction(float(_floats(self.scale)[0]), float(grid_max), majorant, cells)
        if self.volume is None:
            self._check_voxel_optical_depth(float(majorant))
        #: what tracking needs to cut hot majorant segments into tighter pieces
        #: (mitsuba_plugins.walk.refined_piece), or None where no segment can
        #: be hot: then the kernels carry no refinement code at all
        self.refinement = self._voxels if self._has_hot_cells(cells, to_local) else None
        self.global_majorant = dr.opaque(mi.Float, float(majorant))
        self.majorant_grid = MajorantGrid(cells, to_local, float(majorant),
                                          minorants=lows * scale)
        #: the finest bounds, for marches whose steps shrink with the bound (majorant
        #: step mode): the automatic coarsening weighs lookups against tracking's DDA
        #: steps, a march takes step_optical_depth / sigma_maj steps per unit length
        self.march_grid = self.majorant_grid if fine is None else \
            MajorantGrid(fine * scale, to_local, float(majorant))

    def _has_hot_cells(self, cells: np.ndarray, to_local) -> bool:
        """Can a ray cross a majorant cell with optical depth (bound x length) above
        contract.REFINE_OPTICAL_DEPTH? The longest segment in a cell is its longest
        diagonal."""
        from mitsuba_plugins.contract import REFINE_OPTICAL_DEPTH
        if self._voxels is None or not cells.size:
            return False
        linear = _world_linear(to_local)
        rz, ry, rx = cells.shape
        diagonals = [linear @ (np.array([sx, sy, 1.0]) / (rx, ry, rz))
                     for sx in (-1, 1) for sy in (-1, 1)]
        longest = max(float(np.linalg.norm(d)) for d in diagonals)
        return float(np.max(cells)) * longest > REFINE_OPTICAL_DEPTH

    def _check_voxel_optical_depth(self, majorant: float) -> None:
        linear = _world_linear(self.to_local)
        z, y, x = self.shape[:3]
        edge = float(np.min(np.linalg.norm(linear, axis=0) / np.array([x, y, z])))
        depth = majorant * edge
        if depth <= MAX_VOXEL_OPTICAL_DEPTH:
            return
        raise PluginParameterError(
            f"grid_medium: the densest voxel of filename '{self.filename}' has optical depth "
            f"{depth:.3g} (extinction {majorant:.3g} x shortest voxel edge {edge:.3g}); "
            f"allowed: at most {MAX_VOXEL_OPTICAL_DEPTH:g}: lower parameter 'scale' (any "
            "voxel of optical depth above ~50 is opaque)")

    def _check_extinction(self, scale: float, grid_max: float, majorant, cells) -> None:
        """The extinction as the kernels compute it, in float32: finite and at most
        :data:`MAX_EXTINCTION`, the majorants included (checking the doubles would let
        scale = 1e39, inf in float32, through)."""
        top = max(float(majorant), float(np.max(cells)) if cells.size else 0.0)
        if np.isfinite(np.float32(scale)) and np.isfinite(top) and top <= MAX_EXTINCTION:
            return
        source = f"filename '{self.filename}'" if self.filename else "the sigma_t volume"
        raise PluginParameterError(
            f"grid_medium: extinction too large: parameter 'scale' = {scale:g} times the "
            f"largest density of {source} (times sigma_t), {grid_max:g}, gives a majorant "
            f"of {top:g} in float32; allowed: a product of at most {MAX_EXTINCTION:g} per "
            "unit length")

    def _majorant_builder(self):
        """A filled :class:`MajorantBuilder` for the current data, and the grid's
        world -> local transform; ``(None, transform)`` for a volume without data."""
        if self.sparse is not None and int(np.prod(self.shape[:3])) > EXACT_MAJORANT_VOXELS:
            return "bricks", self.to_local
        if self.sparse is not None:
            index = self.brick_extrema[2]
            pool = self.sparse.pool.numpy().reshape(-1, *(bricks.SIDE,) * 3, self.channels)
            data = bricks.densify(index, pool, self.shape)
            weights = _weights(_floats(self.sigma_t_factor), self.channels)
            margin, to_local = MARGIN, self.to_local
        elif self.volume is None:
            data = self.data.numpy()
            gridio.check_values(self.filename, "density", data)
            weights = _weights(_floats(self.sigma_t_factor), self.channels)
            margin, to_local = MARGIN, self.to_local
        else:
            data, to_local = _volume_grid(self.volume)
            if data is None:
                return None, _bbox_to_local(self.bbox)
            weights, margin = 1.0, PARSED_TRANSFORM_MARGIN
        builder = MajorantBuilder(data.shape, resolution_for(data.shape, self.cells), weights,
                                  margin)
        builder.add_all(data)
        return builder, to_local

    # -- mi.Medium interface ---------------------------------------------------------
    def intersect_aabb(self, ray: mi.Ray3f):
        return ray_box(ray.o, ray.d, self.bbox.min, self.bbox.max)

    def get_majorant(self, mei: mi.MediumInteraction3f, active: mi.Bool = True) -> mi.Color3f:
        # One gray value for all channels: volpath picks one channel's majorant for
        # distance sampling and is unbiased only when it bounds every channel.
        return mi.Color3f(self.global_majorant)

    def eval_sigma_t(self, mei: mi.MediumInteraction3f, active: mi.Bool = True) -> mi.Color3f:
        """Extinction at ``mei.p`` (per channel)."""
        if self.volume is not None:
            sigma_t = self.scale * self.volume.eval(mei, active)
        elif self.sparse is not None:
            value = self.sparse.eval(mi.Transform4f(self.to_local) @ mei.p,
                                     self.interpolation == "trilinear", active)
            rho = mi.Color3f(value) if self.channels == 1 else value
            sigma_t = self.scale * rho * self.sigma_t_factor
        else:
            value = self.texture.eval(mi.Transform4f(self.to_local) @ mei.p, active)
            rho = mi.Color3f(value[0]) if self.channels == 1 else mi.Color3f(*value)
            sigma_t = self.scale * rho * self.sigma_t_factor
        if mi.has_flag(self.phase_function().flags(), mi.PhaseFunctionFlags.Microflake):
            sigma_t *= self.phase_function().projected_area(mei, active)
        return sigma_t

    def eval_albedo(self, mei: mi.MediumInteraction3f, active: mi.Bool = True):
        """Single-scattering albedo at ``mei.p`` (per channel)."""
        return self.albedo.eval(mei, active)

    def get_scattering_coefficients(self, mei: mi.MediumInteraction3f, active: mi.Bool = True):
        sigma_t = self.eval_sigma_t(mei, active)
        sigma_s = sigma_t * self.eval_albedo(mei, active)
        sigma_n = mi.Color3f(self.global_majorant) - sigma_t
        return sigma_s, sigma_n, sigma_t

    @property
    def has_emission(self) -> bool:
        return self.emission is not None

    def get_radiance(self, mei: mi.MediumInteraction3f, active: mi.Bool = True) -> mi.Color3f:
        """Emitted radiance :math:`L_e` at ``mei.p`` (0 without ``emission``); an
        integrator adds :math:`\\sigma_a L_e` per unit length (docs/method.md section 6)."""
        if self.emission is None:
            return mi.Color3f(0.0)
        radiance = mi.Color3f(self.emission.eval(mei, active))
        if self.emission_grid is not None:
            grid, to_local = self.emission_grid
            value = grid.eval(mi.Transform4f(to_local) @ mei.p,
                              self.interpolation == "trilinear", active)
            radiance *= mi.Color3f(value) if grid.channels == 1 else value
        return radiance

    def traverse(self, callback):
        flags = mi.ParamFlags.NonDifferentiable
        callback.put("scale", self.scale, flags)
        if self.volume is not None:
            callback.put("sigma_t", self.volume, mi.ParamFlags.Differentiable)
        else:
            if self.sparse is None:
                # differentiable: prbvolpath's gradient w.r.t. it equals the one with
                # heterogeneous + gridvolume (tests/test_gradients.py)
                callback.put("data", self.data, mi.ParamFlags.Differentiable)
            callback.put("sigma_t", self.sigma_t_factor, flags)
        callback.put("albedo", self.albedo, mi.ParamFlags.Differentiable)
        if self.emission is not None:
            callback.put("emission", self.emission, mi.ParamFlags.Differentiable)
        callback.put("phase_function", self.phase_function(), mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys=None):
        scale = _floats(self.scale)[0]
        if not (np.isfinite(scale) and scale >= 0):
            raise PluginParameterError(
                f"grid_medium: parameter 'scale' = {scale!r} is invalid; allowed: a finite "
                "number >= 0")
        factor = _floats(self.sigma_t_factor)
        if not all(np.isfinite(f) and f >= 0 for f in factor):
            raise PluginParameterError(
                f"grid_medium: parameter 'sigma_t' = {factor} is invalid; allowed: finite "
                "values >= 0")
        _check_volume_range("albedo", self.albedo, 0.0, 1.0)
        if self.volume is None and self.sparse is None:
            if tuple(self.data.shape) != tuple(self.texture.tensor().shape):
                raise PluginParameterError(
                    f"grid_medium: parameter 'data' changed shape from "
                    f"{tuple(self.texture.tensor().shape)} to {tuple(self.data.shape)}")
            self.texture.set_tensor(self.data)
        elif self.volume is not None:
            _check_volume_range("sigma_t", self.volume, 0.0, None)
        self._update_majorants()

    def to_string(self) -> str:
        source = f"filename = '{self.filename}'" if self.filename else \
            f"sigma_t = {self.volume.class_name()}"
        rx, ry, rz = self.majorant_grid.resolution
        if self.sparse is not None:
            source += (f",\n  storage = sparse ({self.sparse.stored - 1} bricks stored, "
                       f"{self.sparse.nbytes / 2**20:.1f} MiB)")
        return (f"GridMedium[\n  {source},\n  channels = {self.channels},\n"
                f"  scale = {_floats(self.scale)[0]:g},\n"
                f"  global_majorant = {_floats(self.global_majorant)[0]:g},\n"
                f"  majorant_grid = {rx} x {ry} x {rz} (empty fraction "
                f"{self.majorant_grid.empty_fraction():.3f}),\n"
                f"  emission = {self.emission is not None}\n]")


def _vdb_to_world(header, to_world: mi.ScalarTransform4f) -> mi.ScalarTransform4f:
    """Unit cube of a .vdb grid's loaded box -> world (OpenVDB placement): the file's
    index-to-world transform, then ``to_world``; composed and inverted in double
    precision, float32 only at the end."""
    from mitsuba_plugins.vdb import grid_to_world
    matrix = np.array(to_world.matrix, dtype=np.float64) @ grid_to_world(header)
    return mi.ScalarTransform4f(dr.scalar.Matrix4f(matrix.astype(np.float32)),
                                dr.scalar.Matrix4f(np.linalg.inv(matrix).T.astype(np.float32)))


def _read_bricks(header, what: str) -> bricks.BrickBuilder:
    """A filled :class:`~mitsuba_plugins.bricks.BrickBuilder` of a grid file, every value
    checked (finite, >= 0; ``what`` names the data in errors). For a .vdb the OpenVDB
    worker cuts the bricks and only stored ones cross the pipe (a non-finite or negative
    value is non-zero, so its brick is among the checked ones)."""
    builder = bricks.BrickBuilder(header.shape)
    if header.vdb_grid is not None:
        from mitsuba_plugins.vdb import iter_vdb_bricks
        for row, cols, blocks in iter_vdb_bricks(header):
            gridio.check_values(header.path, what, blocks)
            builder.add_row(row, cols, blocks)
    else:
        for z0, slab in gridio.iter_slabs(header):
            gridio.check_values(header.path, what, slab)
            builder.add(z0, slab)
    builder.finish_check()
    return builder


def _load_emission_grid(path: str, name: str, to_world: mi.ScalarTransform4f):
    """``(SparseGrid, world -> local)`` of grid ``name`` of a .vdb (values >= 0)."""
    from mitsuba_plugins.sparse import SparseGrid
    header = gridio.read_header(path, name)
    builder = _read_bricks(header, f"emission_grid {name!r}")
    grid = SparseGrid(header.shape, builder.index, builder.pool_chunks(), builder.stored)
    return grid, _vdb_to_world(header, to_world).inverse()


# -- parameter helpers ----------------------------------------------------------------
def _floats(value) -> list:
    """Python floats of a scalar, Color or Dr.Jit array of width 1."""
    if isinstance(value, (int, float)):
        return [float(value)]
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    return [float(v) for v in arr]


def _color(p: Params, name: str, default: float) -> list:
    """A non-negative float or rgb parameter as three floats."""
    value = p.props[name] if p.has(name) else default
    if isinstance(value, mi.Object):
        raise PluginParameterError(
            f"grid_medium: parameter '{name}' must be a float or rgb multiplier when "
            f"'filename' is given (got a {value.class_name()})")
    try:
        values = _floats(value)
    except (TypeError, ValueError):
        raise PluginParameterError(
            f"grid_medium: parameter '{name}' = {value!r} is invalid; allowed: a float or rgb "
            ">= 0") from None
    values = values * 3 if len(values) == 1 else values
    if len(values) != 3 or not all(np.isfinite(v) and v >= 0 for v in values):
        raise PluginParameterError(
            f"grid_medium: parameter '{name}' = {values} is invalid; allowed: finite values "
            ">= 0")
    return values


def _volume(p: Params, name: str, default, hi: float | None = None) -> mi.Volume:
    """A float, rgb or nested volume parameter as a ``mi.Volume``, range-checked."""
    value = p.props[name] if p.has(name) else default
    if isinstance(value, mi.Volume):
        _check_volume_range(name, value, 0.0, hi)
        return value
    if isinstance(value, mi.Object):
        raise PluginParameterError(
            f"grid_medium: parameter '{name}' must be a float, rgb or volume (got a "
            f"{value.class_name()})")
    values = _color(p, name, default)
    if hi is not None and max(values) > hi:
        raise PluginParameterError(
            f"grid_medium: parameter '{name}' = {values} is invalid; allowed: values in "
            f"[0, {hi:g}]")
    spec = values[0] if len(set(values)) == 1 else {"type": "rgb", "value": values}
    return mi.load_dict({"type": "constvolume", "value": spec})


def _check_volume_range(name: str, volume: mi.Volume, lo: float, hi: float | None) -> None:
    data, _ = _volume_grid(volume, need_transform=False)
    if data is not None:
        gridio.check_values(f"<{name} volume>", name, data, lo, hi)
        return
    vmax = float(volume.max())
    if not np.isfinite(vmax) or (hi is not None and vmax > hi):
        raise PluginParameterError(
            f"grid_medium: parameter '{name}' has maximum {vmax:g}; allowed: values in "
            f"[{lo:g}, {'inf' if hi is None else f'{hi:g}'}]")


def _weights(factor, channels: int) -> np.ndarray:
    """Per-channel weights of the grid for the gray majorant."""
    factor = np.asarray(factor, dtype=np.float32)
    return np.array([factor.max()], np.float32) if channels == 1 else factor


def _check_invertible(value) -> None:
    """Refuse a ``to_world`` that is singular (a zero scale makes the medium vanish) or
    holds non-finite numbers."""
    matrix = np.array(value.matrix, dtype=np.float64)
    linear = matrix[:3, :3]
    det = float(np.linalg.det(linear)) if np.all(np.isfinite(matrix)) else float("nan")
    size = float(np.max(np.abs(linear))) if np.all(np.isfinite(linear)) else 0.0
    if not (np.isfinite(det) and abs(det) > SINGULAR_TOLERANCE * size ** 3 and size > 0):
        raise PluginParameterError(
            f"grid_medium: parameter 'to_world' is singular or not finite (determinant of "
            f"its 3x3 part {det:g}); allowed: an invertible transform (no zero scale)")


def _world_linear(to_local) -> np.ndarray:
    """The 3x3 linear part of a grid's local -> world map (columns: the world images of
    the local unit axes)."""
    return np.array(to_local.inverse().matrix, dtype=np.float64)[:3, :3]


def _transform(value) -> mi.ScalarTransform4f:
    """A Properties transform (double precision) as a float transform."""
    return mi.ScalarTransform4f(dr.scalar.Matrix4f(value.matrix),
                                dr.scalar.Matrix4f(value.inverse_transpose))


def _world_bbox(to_local: mi.ScalarTransform4f) -> mi.ScalarBoundingBox3f:
    to_world = to_local.inverse()
    bbox = mi.ScalarBoundingBox3f()
    for corner in range(8):
        bbox.expand(to_world @ mi.ScalarPoint3f(corner & 1, (corner >> 1) & 1, corner >> 2))
    return bbox


def _bbox_to_local(bbox) -> mi.ScalarTransform4f:
    lo = np.array(bbox.min, dtype=np.float32)
    extent = np.maximum(np.array(bbox.max, dtype=np.float32) - lo, 1e-30)
    return mi.ScalarTransform4f().scale(1.0 / extent).translate(-lo)


_MATRIX = re.compile(r"to_local = Transform\[\s*matrix=\[(.*?)\]\],", re.S)


def _volume_grid(volume: mi.Volume, need_transform: bool = True):
    """``(data (Z, Y, X, C) numpy or None, to_local)`` of a Mitsuba volume.

    Only grid volumes expose data. Mitsuba does not expose a volume's transform, so it is
    read back from ``to_string()`` (6 significant digits; the majorant cells get a
    matching margin), and checked against the volume's bounding box.
    """
    params = mi.traverse(volume)
    if "data" not in params:
        return None, None
    data = np.asarray(params["data"].numpy(), dtype=np.float32)
    if data.ndim == 3:
        data = data[..., None]
    if not need_transform:
        return data, None
    match = _MATRIX.search(str(volume))
    to_local = None
    if match:
        rows = re.findall(r"\[([^\[\]]*)\]", match.group(1) + "]")
        try:
            matrix = np.array([[float(v) for v in r.split(",")] for r in rows], np.float32)
            to_local = mi.ScalarTransform4f(matrix) if matrix.shape == (4, 4) else None
        except ValueError:
            to_local = None
    bbox = volume.bbox()
    if to_local is not None:
        ours = _world_bbox(to_local)
        size = float(np.max(np.abs(np.array(bbox.max) - np.array(bbox.min))))
        err = max(float(np.max(np.abs(np.array(ours.min) - np.array(bbox.min)))),
                  float(np.max(np.abs(np.array(ours.max) - np.array(bbox.max)))))
        if not err <= 1e-4 * max(size, 1.0):
            to_local = None
    if to_local is None:
        # Unreadable transform: one cell over the bounding box, still a valid bound.
        return None, None
    return data, to_local


mi.register_medium("grid_medium", lambda props: GridMedium(props))
