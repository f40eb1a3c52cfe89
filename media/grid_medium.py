"""Heterogeneous grid medium with a majorant grid; a drop-in for Mitsuba's ``heterogeneous``."""
from __future__ import annotations

import re

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins import bricks, gridio
from mitsuba_plugins.majorant import (DEFAULT_RESOLUTION, MARGIN, MajorantBuilder, MajorantGrid,
                                      ProductMajorantBuilder, auto_resolution, pool, ray_box,
                                      resolution_for, voxel_ranges)
from mitsuba_plugins.params import Params, PluginParameterError
from mitsuba_plugins.spectra import MODEL_CHANNELS, GridValues, Multiplier, model_range

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
        self.emission = _volume(p, "emission", None, illuminant=True) \
            if p.has("emission") else None
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
                    self.emission = _volume(p, "emission", 1.0, illuminant=True)
                self.emission_grid = _load_emission_grid(self.filename,
                                                         p.props["emission_grid"], to_world)
            is_vdb = self.filename.lower().endswith(".vdb")
            self.storage = p.choice("storage", "auto" if is_vdb else "dense", STORAGES)
            self.sigma_t_factor = mi.Color3f(factor)
            self.multiplier = Multiplier(factor)
            data, to_local, bbox, builder = self._load(self.filename, to_world,
                                                       p.bool("use_grid_bbox", False))
            if data is not None:
                self.data = data
                self.texture = mi.Texture3f(data, use_accel=True, migrate=True,
                                            filter_mode=INTERPOLATIONS[self.interpolation],
                                            wrap_mode=dr.WrapMode.Clamp)
            self.to_local = to_local
            self.bbox = bbox
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
            self.multiplier = Multiplier(1.0)
            self._voxels = None  # a nested volume's lookups are Mitsuba's own
            builder = None
        self.scale = mi.Float(scale)
        chromatic = self.channels == 3 or len(set(_floats(self.sigma_t_factor))) > 1
        self.m_has_spectral_extinction = p.bool("has_spectral_extinction", chromatic)
        self.m_is_homogeneous = False
        self.is_chromatic = chromatic
        self._update_majorants(builder)

    # -- loading ---------------------------------------------------------------------
    def _load(self, path, to_world, use_grid_bbox):
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
        #: what a stored voxel holds in this variant (mitsuba_plugins.spectra)
        self.values = GridValues(header.channels)
        stored = (*header.shape[:3], self.values.channels)
        if self.storage != "dense":
            return self._load_bricks(header, to_local, stored)
        builder = self._new_builder(stored)
        flat = dr.zeros(mi.Float, int(np.prod(stored)))
        slab_elems = int(np.prod(stored[1:]))
        for z0, slab in gridio.iter_slabs(header):
            gridio.check_values(path, "density", slab)
            slab = self.values.convert(slab)
            builder.add(z0, slab)
            values = slab.reshape(-1)
            for start in range(0, values.size, UPLOAD_CHUNK):
                chunk = values[start:start + UPLOAD_CHUNK]
                index = dr.arange(mi.UInt32, z0 * slab_elems + start,
                                  z0 * slab_elems + start + chunk.size)
                dr.scatter(flat, mi.Float(chunk), index)
                dr.eval(flat)
        data = mi.TensorXf(flat, shape=stored)
        return data, to_local, _world_bbox(to_local), builder

    def _new_builder(self, stored_shape, values=None, margin: float = MARGIN):
        """An empty majorant builder for stored grid values of ``stored_shape``: gray
        bounds weighted by the sigma_t multiplier, or, for upsampled RGB (spectral
        variants), the product of the spectrum's and the scale's cell maxima."""
        values = values or self.values
        resolution = resolution_for(stored_shape, self.cells)
        m = self.multiplier
        if values.upsampled:
            return ProductMajorantBuilder(stored_shape, resolution, values.factors, m.upper,
                                          margin)
        return MajorantBuilder(stored_shape, resolution, m.weights(stored_shape[3]), margin)

    def _load_bricks(self, header, to_local, stored):
        """Stream the grid into bricks (:mod:`mitsuba_plugins.bricks`); ``storage =
        auto`` falls back to dense storage when the bricks save less than half."""
        from mitsuba_plugins.sparse import SparseGrid
        builder = _read_bricks(header, "density", self.values)
        index = builder.index
        maxima, minima = builder.extrema()
        sparse_bytes = 4 * (index.size + builder.stored * bricks.SIDE ** 3 * stored[3])
        if self.storage == "auto" and sparse_bytes > AUTO_SPARSE_FRACTION * 4 * np.prod(stored):
            self.storage = "dense"
            _, pool, _, _ = builder.finish()
            data = bricks.densify(index, pool, stored)
            del pool
            majorants = self._new_builder(stored).add_all(data)
            return mi.TensorXf(data), to_local, _world_bbox(to_local), majorants
        self.storage = "sparse"
        self.sparse = SparseGrid(stored, index, builder.pool_chunks(), builder.stored)
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
        m, c = self.multiplier, self.values.channels
        product = self.values.upsampled
        values, lows = bricks.cell_bounds(maxima, minima, index, self.shape, ranges,
                                          m.weights(c), product=product)
        from mitsuba_plugins.majorant import ROUNDING
        grid_max = np.float32(np.prod(maxima.max(axis=0)) * m.upper if product else
                              (maxima * m.weights(c)).max())
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
            grid_max = np.float32(_volume_max(self.volume))
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
        values, margin = self.values if self.volume is None else None, MARGIN
        if self.sparse is not None and int(np.prod(self.shape[:3])) > EXACT_MAJORANT_VOXELS:
            return "bricks", self.to_local
        if self.sparse is not None:
            index = self.brick_extrema[2]
            c = self.sparse.channels
            pool = self.sparse.pool.numpy().reshape(-1, *(bricks.SIDE,) * 3, c)
            data = bricks.densify(index, pool, (*self.shape[:3], c))
            to_local = self.to_local
        elif self.volume is None:
            data = self.data.numpy()
            if not values.converted:   # exposed through traverse: may have been changed
                gridio.check_values(self.filename, "density", data)
            to_local = self.to_local
        else:
            data, to_local = _volume_grid(self.volume)
            if data is None:
                return None, _bbox_to_local(self.bbox)
            # Mitsuba's volume holds RGB (evaluated as luminance in mono) or, in spectral
            # variants, the upsampled model (4 channels) already
            values = GridValues(3 if data.shape[3] == MODEL_CHANNELS else data.shape[3])
            if values.gray_only:
                data = values.convert(data)
            margin = PARSED_TRANSFORM_MARGIN
        builder = self._new_builder(data.shape, values, margin)
        builder.add_all(data)
        return builder, to_local

    # -- mi.Medium interface ---------------------------------------------------------
    def intersect_aabb(self, ray: mi.Ray3f):
        return ray_box(ray.o, ray.d, self.bbox.min, self.bbox.max)

    def get_majorant(self, mei: mi.MediumInteraction3f, active: mi.Bool = True):
        # One gray value for all channels: volpath picks one channel's majorant for
        # distance sampling and is unbiased only when it bounds every channel.
        return mi.UnpolarizedSpectrum(self.global_majorant)

    def eval_sigma_t(self, mei: mi.MediumInteraction3f, active: mi.Bool = True):
        """Extinction at ``mei.p`` (per channel: RGB, or the path's wavelengths)."""
        if self.volume is not None:
            sigma_t = self.scale * self.volume.eval(mei, active)
        else:
            p = mi.Transform4f(self.to_local) @ mei.p
            trilinear = self.interpolation == "trilinear"
            if self.sparse is not None:
                rho = _grid_value(self.sparse, self.values, p, trilinear, mei.wavelengths,
                                  active)
            elif self.values.upsampled and trilinear:
                rho = self.values.blend(self.texture.eval_fetch(p, active),
                                        _cell_position(p, self.shape), mei.wavelengths)
            else:
                rho = self.values.spectrum(self.texture.eval(p, active), mei.wavelengths)
            sigma_t = self.scale * rho * self.multiplier.spectrum(mei.wavelengths,
                                                                  self.sigma_t_factor)
        if mi.has_flag(self.phase_function().flags(), mi.PhaseFunctionFlags.Microflake):
            sigma_t *= self.phase_function().projected_area(mei, active)
        return sigma_t

    def eval_albedo(self, mei: mi.MediumInteraction3f, active: mi.Bool = True):
        """Single-scattering albedo at ``mei.p`` (per channel)."""
        return self.albedo.eval(mei, active)

    def get_scattering_coefficients(self, mei: mi.MediumInteraction3f, active: mi.Bool = True):
        sigma_t = self.eval_sigma_t(mei, active)
        sigma_s = sigma_t * self.eval_albedo(mei, active)
        sigma_n = mi.UnpolarizedSpectrum(self.global_majorant) - sigma_t
        return sigma_s, sigma_n, sigma_t

    @property
    def has_emission(self) -> bool:
        return self.emission is not None

    def get_radiance(self, mei: mi.MediumInteraction3f, active: mi.Bool = True):
        """Emitted radiance :math:`L_e` at ``mei.p`` (0 without ``emission``); an
        integrator adds :math:`\\sigma_a L_e` per unit length (docs/method.md section 6)."""
        if self.emission is None:
            return mi.UnpolarizedSpectrum(0.0)
        radiance = mi.UnpolarizedSpectrum(self.emission.eval(mei, active))
        if self.emission_grid is not None:
            grid, values, to_local = self.emission_grid
            radiance *= _grid_value(grid, values, mi.Transform4f(to_local) @ mei.p,
                                    self.interpolation == "trilinear", mei.wavelengths,
                                    active)
        return radiance

    def traverse(self, callback):
        flags = mi.ParamFlags.NonDifferentiable
        callback.put("scale", self.scale, flags)
        if self.volume is not None:
            callback.put("sigma_t", self.volume, mi.ParamFlags.Differentiable)
        else:
            if self.sparse is None and not self.values.converted:
                # differentiable: prbvolpath's gradient w.r.t. it equals the one with
                # heterogeneous + gridvolume (tests/test_gradients.py). Not exposed where
                # the stored values are not the file's (RGB upsampled in spectral
                # variants, reduced to luminance in mono).
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
        self.multiplier = Multiplier(factor)
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


def _read_bricks(header, what: str, values: GridValues) -> bricks.BrickBuilder:
    """A filled :class:`~mitsuba_plugins.bricks.BrickBuilder` of a grid file, every value
    checked (finite, >= 0; ``what`` names the data in errors) and stored as ``values``
    says (a brick's extrema are then those of the majorant factors of upsampled RGB).
    For a .vdb the OpenVDB worker cuts the bricks and only stored ones cross the pipe (a
    non-finite or negative value is non-zero, so its brick is among the checked ones)."""
    builder = bricks.BrickBuilder((*header.shape[:3], values.channels),
                                  bounds=values.factors if values.upsampled else None)
    if header.vdb_grid is not None:
        from mitsuba_plugins.vdb import iter_vdb_bricks
        for row, cols, blocks in iter_vdb_bricks(header):
            gridio.check_values(header.path, what, blocks)
            builder.add_row(row, cols, values.convert(blocks))
    else:
        for z0, slab in gridio.iter_slabs(header):
            gridio.check_values(header.path, what, slab)
            builder.add(z0, values.convert(slab))
    builder.finish_check()
    return builder


def _load_emission_grid(path: str, name: str, to_world: mi.ScalarTransform4f):
    """``(SparseGrid, GridValues, world -> local)`` of grid ``name`` of a .vdb (values
    >= 0)."""
    from mitsuba_plugins.sparse import SparseGrid
    header = gridio.read_header(path, name)
    values = GridValues(header.channels)
    builder = _read_bricks(header, f"emission_grid {name!r}", values)
    grid = SparseGrid((*header.shape[:3], values.channels), builder.index,
                      builder.pool_chunks(), builder.stored)
    return grid, values, _vdb_to_world(header, to_world).inverse()


def _grid_value(grid, values: GridValues, p: mi.Point3f, trilinear: bool, wavelengths,
                active) -> mi.UnpolarizedSpectrum:
    """The value of a sparse grid (:class:`~mitsuba_plugins.sparse.SparseGrid`) at local
    point ``p`` as a spectrum (upsampled RGB: Mitsuba's blend, mitsuba_plugins.spectra)."""
    if values.upsampled:
        if trilinear:
            corners, f = grid.fetch(p, active)
            return values.blend(corners, f, wavelengths)
        return values.spectrum(grid.eval(p, False, active), wavelengths)
    value = grid.eval(p, trilinear, active)
    return mi.UnpolarizedSpectrum(value) if grid.channels == 1 else value


def _cell_position(p: mi.Point3f, shape) -> mi.Vector3f:
    """Where local ``p`` lies between the voxel centres that a trilinear texture lookup
    blends (``gridvolume``'s weights for ``Texture3f.eval_fetch``)."""
    z, y, x = shape[:3]
    q = dr.fma(p, mi.Vector3f(x, y, z), -0.5)
    return q - dr.floor(q)


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


def _volume(p: Params, name: str, default, hi: float | None = None,
            illuminant: bool = False) -> mi.Volume:
    """A float, rgb or nested volume parameter as a ``mi.Volume``, range-checked.

    In spectral variants a constant is upsampled by Mitsuba's rules: ``illuminant``
    (emission) as an emitter's radiance is (``d65``: an RGB white renders white, as an
    area light of the same value does), otherwise as a reflectance (``rgb``: values in
    [0, 1], as ``homogeneous`` requires of its ``sigma_t``)."""
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
    if illuminant and mi.is_spectral:
        spec = {"type": "d65", "color": values}
    elif len(set(values)) == 1:
        spec = values[0]
    else:
        if mi.is_spectral and max(values) > 1:
            raise PluginParameterError(
                f"grid_medium: parameter '{name}' = {values} is invalid in the spectral "
                f"variant '{mi.variant()}'; allowed: rgb values in [0, 1] (upsampled as a "
                "reflectance, as for Mitsuba's media): divide them by their maximum and "
                "multiply 'scale' by it")
        spec = {"type": "rgb", "value": values}
    return mi.load_dict({"type": "constvolume", "value": spec})


def _check_volume_range(name: str, volume: mi.Volume, lo: float, hi: float | None) -> None:
    data, _ = _volume_grid(volume, need_transform=False)
    if data is not None:
        if mi.is_spectral and data.shape[3] == MODEL_CHANNELS:
            # Mitsuba's upsampled RGB: check the values it takes over the wavelengths
            gridio.check_values(f"<{name} volume>", name, data)   # finite
            s_min, s_max = model_range(data)
            data = np.stack([s_min * data[..., 3], s_max * data[..., 3]], axis=-1)
        gridio.check_values(f"<{name} volume>", name, data, lo, hi)
        return
    vmax = _volume_max(volume)
    if not np.isfinite(vmax) or (hi is not None and vmax > hi):
        raise PluginParameterError(
            f"grid_medium: parameter '{name}' has maximum {vmax:g}; allowed: values in "
            f"[{lo:g}, {'inf' if hi is None else f'{hi:g}'}]")


#: relative slack on a constant volume's largest value read at sampled wavelengths
PROBE_SLACK = 1e-3


def _volume_max(volume: mi.Volume) -> float:
    """A bound of a volume without grid data: Mitsuba's ``max()``, and in spectral
    variants also the largest value over the visible range (Mitsuba's ``max()`` of an
    upsampled rgb constant is not one: 0.84 for (1, 0.2, 1), whose spectrum reaches
    0.9998), read at the centre of its box."""
    vmax = float(volume.max())
    if mi.is_spectral:
        from mitsuba_plugins.contract import probe_wavelengths
        it = dr.zeros(mi.Interaction3f, 256)
        it.wavelengths = probe_wavelengths(256)
        it.p = mi.Point3f(volume.bbox().center())
        probed = float(np.max(np.asarray(volume.eval(it))))
        vmax = max(vmax, probed * (1 + PROBE_SLACK))
    return vmax


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
