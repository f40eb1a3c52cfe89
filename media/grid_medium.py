"""Heterogeneous grid medium with a majorant grid; a drop-in for Mitsuba's ``heterogeneous``.

The plugin: its parameters and Mitsuba's medium interface. Where the values live is a
store (:mod:`mitsuba_plugins.grids.stores`), how a grid is placed :mod:`mitsuba_plugins.grids.placement`,
its majorants :func:`mitsuba_plugins.tracking.majorant.derive`, RGB in other variants
:mod:`mitsuba_plugins.grids.spectra`.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_plugins.grids import gridio, nested_volume, placement, side_grids, stores
from mitsuba_plugins.grids.side_grids import SideGrids
from mitsuba_plugins.grids.spectra import Multiplier
from mitsuba_plugins.grids.value_checks import check_float32, checked_factors
from mitsuba_plugins.params import Params, PluginParameterError, floats
from mitsuba_plugins.tracking import majorant
from mitsuba_plugins.tracking.majorant_grid import ray_box

VARIANT = mi.variant()


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
         :mod:`mitsuba_plugins.grids.vdb_openvdb`). Without it, ``sigma_t`` is the extinction itself,
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
     * - albedo_grid
       - |string|
       - Colour grid: a grid of the same ``.vdb`` file (float or vec3s, e.g. ``Cd`` or
         ``color``) that multiplies ``albedo`` (which defaults to 1 when this is given),
         placed by its own transform (then ``to_world``), interpolated as the density,
         stored in bricks; the product must stay in [0, 1]. (Default: none)
     * - temperature_grid
       - |string|
       - Fire: a float grid of the same ``.vdb`` file (e.g. ``temperature``) whose
         temperature :math:`T = (v - o)\,s` makes the emitted radiance ``emission`` x
         the blackbody spectrum normalised to a peak of 1 (pbrt-v4's ``nanovdb`` rule;
         0 at or below 100 K; :mod:`mitsuba_plugins.grids.blackbody`: linear sRGB in RGB
         variants, clamped at 0, Planck's law at the path's wavelengths in spectral
         ones, where ``emission`` is then a plain factor, not an illuminant: spectral and
         RGB renders agree). ``emission`` defaults to 1; not with ``emission_grid``.
         (Default: none)
     * - temperature_offset
       - |float|
       - :math:`o`, subtracted from the grid's value first (pbrt's
         ``temperatureoffset``). (Default: 0)
     * - temperature_scale
       - |float|
       - :math:`s`, kelvin per unit of the grid after the offset, > 0 (pbrt's
         ``temperaturescale``); the hottest voxel must stay at or below 1e5 K.
         (Default: 1)
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
    per-cell bounds and a DDA (:mod:`mitsuba_plugins.tracking.majorant`) for our integrators.
    With a nested ``sigma_t`` volume and no ``filename`` it renders exactly what
    ``heterogeneous`` renders.

    The ``filename`` grid is streamed from disk in slabs into one device buffer: peak
    memory is about one copy of the raw grid (``gridvolume`` holds two), or, stored
    sparse, about the brick pool (:mod:`mitsuba_plugins.grids.bricks`).

    ``mi.traverse`` exposes ``scale``, ``sigma_t`` (the multiplier), ``albedo``,
    ``emission`` and the phase function's parameters; with dense storage also ``data``,
    the grid tensor (same shape; the majorants are rebuilt on update), with sparse storage
    ``bricks``, the brick pool (which bricks exist is fixed:
    :mod:`mitsuba_plugins.grids.sparse`), and with ``emission_grid`` its ``emission_bricks``.
    All are differentiable with ``volpath_delta`` (``sigma_t`` in RGB variants only;
    ``data`` and ``albedo`` also with ``prbvolpath``).
    """

    #: implements mitsuba_plugins.tracking.medium_protocol.TrackedMedium (majorant_grid, refinement,
    #: eval_sigma_t, eval_albedo, get_radiance, has_emission, is_chromatic, bbox)
    PROVIDES_TRACKING = True

    ALLOWED = ("filename", "grid", "sigma_t", "scale", "albedo", "emission", "interpolation",
               "to_world", "use_grid_bbox", "majorant_resolution", "has_spectral_extinction",
               "sample_emitters", "storage", "emission_grid", "temperature_grid",
               "temperature_offset", "temperature_scale", "albedo_grid")
    FILE_ONLY = ("interpolation", "to_world", "use_grid_bbox", "grid", "storage",
                 "emission_grid", "temperature_grid", "temperature_offset",
                 "temperature_scale", "albedo_grid")

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        p = Params(props, "grid_medium", self.ALLOWED, objects=(mi.PhaseFunction,))
        scale = check_float32("scale", p.float("scale", 1.0, lo=0.0))
        # 1 when only an albedo_grid gives it
        self.albedo = p.volume("albedo", 1.0 if p.has("albedo_grid") else 0.75, hi=1.0)
        nested_volume.check_volume_range("grid_medium", "albedo", self.albedo, 0.0, 1.0)
        # with a temperature grid, emission scales Planck's spectrum itself: in spectral
        # variants a plain multiplier, not an illuminant (whose d65 shape would tint it)
        self.emission = p.volume("emission", None, illuminant=not p.has("temperature_grid")) \
            if p.has("emission") else None
        #: emission_grid, temperature_grid, albedo_grid of a .vdb
        self.side = SideGrids()
        self.cells = p.int("majorant_resolution", majorant.DEFAULT_RESOLUTION, lo=1, hi=1024)
        #: not given: coarsen the bounds per grid (majorant.auto_resolution)
        self.auto_cells = not p.has("majorant_resolution")
        self.filename = None
        self.interpolation = "trilinear"
        if p.has("filename"):
            self._load_file(p)
        else:
            self.store = nested_volume.VolumeStore.from_params(p, self.FILE_ONLY)
            self.bbox = self.store.volume.bbox()
            self.sigma_t_factor = mi.Color3f(1.0)
            self.multiplier = Multiplier(1.0)
            self._voxels = None  # a nested volume's lookups are Mitsuba's own
        self.scale = mi.Float(scale)
        # opaque, not literals: a literal 0 channel (sigma_t = (1, 1e-4, 0)) was folded
        # into a constant of the first render's width, and a render at another spp then
        # failed ("operands have incompatible sizes"); opaque values also reuse the kernel
        dr.make_opaque(self.scale, self.sigma_t_factor)
        #: the last accepted scale and sigma_t factor (put back where an edit is refused)
        self._accepted = (scale, floats(self.sigma_t_factor))
        self._fold_gray_factor()
        #: the user's has_spectral_extinction, or None: derived from the extinction
        self._spectral_extinction = p.bool("has_spectral_extinction", False) \
            if p.has("has_spectral_extinction") else None
        self.m_is_homogeneous = False
        self._update_chromatic()
        #: the majorant cells' shape and the hot-cell refinement, both chosen at load and
        #: kept across edits (_update_majorants)
        self._majorant_cells, self.refinement = None, None
        self._update_majorants()

    def _update_chromatic(self) -> None:
        """``is_chromatic`` (and ``has_spectral_extinction`` unless given) from the grid's
        channels and the ``sigma_t`` factor, again after every parameter change: an edit
        that made a gray factor chromatic once left both false (silently wrong)."""
        if self.store.kind == "volume":
            self.channels = nested_volume.volume_channels(self.store.volume)
        self.is_chromatic = self.channels == 3 or len(set(floats(self.sigma_t_factor))) > 1
        self.m_has_spectral_extinction = self.is_chromatic \
            if self._spectral_extinction is None else self._spectral_extinction

    def _load_file(self, p: Params) -> None:
        """The ``filename`` grid, placed and stored as its parameters say."""
        self.filename = str(mi.file_resolver().resolve(p.props["filename"]))
        factor = p.color("sigma_t", 1.0, "a float or rgb multiplier when 'filename' is given")
        self.interpolation = p.choice("interpolation", "trilinear", tuple(stores.INTERPOLATIONS))
        to_world = placement.transform(p.props["to_world"]) if p.has("to_world") else \
            mi.ScalarTransform4f()
        if p.has("to_world"):
            placement.check_invertible(p.props["to_world"])
        is_vdb = self.filename.lower().endswith(".vdb")
        for name in ("grid", *side_grids.NAMES):
            if p.has(name) and not is_vdb:
                raise PluginParameterError(
                    f"grid_medium: parameter '{name}' selects a grid of a .vdb file; "
                    f"'{self.filename}' is not one")
        self.emission = self.side.load(p, self.filename, to_world, self.emission)
        self.side.check_albedo(self.albedo)
        storage = p.choice("storage", "auto" if is_vdb else "dense", stores.STORAGES)
        self.sigma_t_factor = mi.Color3f(factor)
        self.multiplier = Multiplier(factor)
        header = gridio.read_header(self.filename, p.props["grid"] if p.has("grid") else "density")
        to_local = placement.grid_to_local(header, to_world, p.bool("use_grid_bbox", False),
                                           self.filename)
        self.store = stores.load(header, storage, self.interpolation, to_local,
                                 self.multiplier, self.cells)
        self.to_local, self.shape = to_local, header.shape
        self.bbox = placement.world_bbox(to_local)
        self.channels = header.channels
        z, y, x = header.shape[:3]
        # voxels per local unit on each axis, and whether lookups are trilinear
        self._voxels = (mi.Vector3f(x, y, z), self.interpolation == "trilinear")

    # -- what the store holds, for tools and tests -----------------------------------
    @property
    def storage(self) -> str:
        return self.store.kind

    @property
    def sparse(self):
        """The :class:`~mitsuba_plugins.grids.sparse.SparseGrid` of sparse storage, else None."""
        return getattr(self.store, "grid", None)

    @property
    def data(self):
        return self.store.data

    @property
    def control_scale(self) -> float:
        """The factor that makes the majorant grid's gray minorant a lower bound of every
        channel (:class:`~mitsuba_plugins.grids.bounds.MajorantBuilder` takes it with the
        multiplier's largest channel where one weight serves all: 1-channel or upsampled
        data), for controls that must stay below the extinction (decomposition tracking)."""
        m = self.multiplier
        single = self.filename is not None and (self.store.values.channels == 1
                                                or self.store.values.upsampled)
        return m.lower / m.upper if single and m.upper > 0 else 1.0

    def _fold_gray_factor(self) -> None:
        """``gray_scale``: ``scale`` times a gray ``sigma_t`` factor, one opaque scalar, in
        RGB variants (None otherwise: the factor is a spectrum). Multiplying each lookup by
        the opaque factor's three channels cost 3-4% of a single-scattering march on the
        sparse puffs (issue 25's A/B)."""
        self.gray_scale = None
        if mi.is_rgb and self.multiplier.gray:
            self.gray_scale = mi.Float(self.scale * self.sigma_t_factor[0])
            dr.make_opaque(self.gray_scale)

    def _update_majorants(self) -> None:
        """(Re)derive the global majorant and the majorant grid from the current data.
        After an edit the cells keep the shape chosen at load and hot-cell refinement,
        once on, stays on: an optimiser's steps change values, not kernels (issue 48)."""
        bounds = self.store.bounds(self.multiplier, self.cells, self.filename)
        source = f"filename '{self.filename}'" if self.filename else "the sigma_t volume"
        m = majorant.derive(bounds.values, bounds.lows, bounds.grid_max, floats(self.scale)[0],
                            bounds.to_local, auto=self.auto_cells, voxels=self._voxels,
                            shape=None if self.filename is None else self.shape,
                            plugin="grid_medium", source=source, cells=self._majorant_cells)
        self._majorant_cells = m.cells
        self.global_majorant = m.global_majorant
        self.majorant_grid = m.grid
        #: the finest bounds, for marches whose steps shrink with the bound
        self.march_grid = m.march_grid
        #: what tracking needs to cut hot majorant segments into tighter pieces
        #: (mitsuba_plugins.tracking.walk.refined_piece), or None where no segment can be hot:
        #: then the kernels carry no refinement code at all
        self.refinement = m.refinement if m.refinement is not None else self.refinement

    # -- mi.Medium interface ---------------------------------------------------------
    def intersect_aabb(self, ray: mi.Ray3f):
        return ray_box(ray.o, ray.d, self.bbox.min, self.bbox.max)

    def get_majorant(self, mei: mi.MediumInteraction3f, active: mi.Bool = True):
        # One gray value for all channels: volpath picks one channel's majorant for
        # distance sampling and is unbiased only when it bounds every channel.
        return mi.UnpolarizedSpectrum(self.global_majorant)

    def eval_sigma_t(self, mei: mi.MediumInteraction3f, active: mi.Bool = True):
        """Extinction at ``mei.p`` (per channel: RGB, or the path's wavelengths)."""
        if self.filename is None:
            sigma_t = self.scale * self.store.eval(mei, active)
        else:
            rho = self.store.eval(mi.Transform4f(self.to_local) @ mei.p, mei.wavelengths,
                                  active)
            # the folded scalar carries the gradient of the factor's first channel
            # only: a differentiated factor stays per channel, whatever its value
            # (a gray factor's G-channel gradient landed on R: issue 46)
            if self.gray_scale is not None and not dr.grad_enabled(self.sigma_t_factor):
                sigma_t = self.gray_scale * rho
            else:
                sigma_t = self.scale * rho * self.multiplier.spectrum(mei.wavelengths,
                                                                      self.sigma_t_factor)
        if mi.has_flag(self.phase_function().flags(), mi.PhaseFunctionFlags.Microflake):
            sigma_t *= self.phase_function().projected_area(mei, active)
        return sigma_t

    def eval_albedo(self, mei: mi.MediumInteraction3f, active: mi.Bool = True):
        """Single-scattering albedo at ``mei.p`` (per channel)."""
        albedo = self.albedo.eval(mei, active)
        if self.side.albedo is not None:
            albedo = albedo * self.side.value(self.side.albedo, mei,
                                              self.interpolation == "trilinear", active)
        return albedo

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
        return self.side.radiance(radiance, mei, self.interpolation == "trilinear", active)

    def traverse(self, callback):
        callback.put("scale", self.scale, mi.ParamFlags.Differentiable)
        self.store.traverse(callback)
        if self.filename is not None:
            # differentiable in RGB variants; elsewhere it is upsampled / reduced on the host
            callback.put("sigma_t", self.sigma_t_factor, mi.ParamFlags.Differentiable
                         if mi.is_rgb else mi.ParamFlags.NonDifferentiable)
        callback.put("albedo", self.albedo, mi.ParamFlags.Differentiable)
        if self.emission is not None:
            callback.put("emission", self.emission, mi.ParamFlags.Differentiable)
        self.side.traverse(callback)
        callback.put("phase_function", self.phase_function(), mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys=None):
        scale, factor = checked_factors(self.scale, self.sigma_t_factor, self._accepted)
        self.multiplier = Multiplier(factor)
        dr.make_opaque(self.scale, self.sigma_t_factor)
        self._accepted = (scale, factor)
        self._fold_gray_factor()
        nested_volume.check_volume_range("grid_medium", "albedo", self.albedo, 0.0, 1.0)
        self.store.changed(keys)
        self._update_chromatic()
        self.side.changed(keys, self.albedo)
        self._update_majorants()

    def to_string(self) -> str:
        source = f"filename = '{self.filename}'" if self.filename else \
            f"sigma_t = {self.store.volume.class_name()}"
        rx, ry, rz = self.majorant_grid.resolution
        return (f"GridMedium[\n  {source}{self.store.describe()},\n"
                f"  channels = {self.channels},\n"
                f"  scale = {floats(self.scale)[0]:g},\n"
                f"  global_majorant = {floats(self.global_majorant)[0]:g},\n"
                f"  majorant_grid = {rx} x {ry} x {rz} (empty fraction "
                f"{self.majorant_grid.empty_fraction():.3f}),\n"
                f"  emission = {self.emission is not None}\n]")


mi.register_medium("grid_medium", lambda props: GridMedium(props))
