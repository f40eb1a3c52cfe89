"""Where a grid medium's values live: one store per kind, with one interface.

* :class:`DenseStore`: one 3D texture of the loaded box (``storage = dense``);
* :class:`SparseStore`: 8^3-voxel bricks in a pool (:mod:`mitsuba_plugins.grids.sparse`);
* :class:`~mitsuba_plugins.grids.nested_volume.VolumeStore`: a nested Mitsuba volume (``sigma_t`` without ``filename``).

A store answers three things: the grid's value at a point as a spectrum of the variant
(:meth:`eval`; for a file grid before ``scale`` and the multiplier), the bounds a majorant
is derived from (:meth:`bounds`, fed to :func:`mitsuba_plugins.tracking.majorant.derive`) and what
it exposes to ``mi.traverse`` (:meth:`traverse`, :meth:`changed`). :func:`load` streams a
grid file into a dense or sparse store, checking every value; nothing is kept if any
check fails.
"""
from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins.grids import bricks, gridio, placement
from mitsuba_plugins.grids.bounds import (MARGIN, MajorantBuilder, ProductMajorantBuilder,
                                          ROUNDING, resolution_for, voxel_ranges)
from mitsuba_plugins.grids.spectra import GridValues
from mitsuba_plugins.grids.value_checks import ValueCheck, check_dense_memory, checked_edit
from mitsuba_plugins.params import PluginParameterError

#: elements moved to device memory per scatter while loading (bounds the extra memory)
UPLOAD_CHUNK = 1 << 18
INTERPOLATIONS = {"trilinear": dr.FilterMode.Linear, "nearest": dr.FilterMode.Nearest}
STORAGES = ("dense", "sparse", "auto")
#: ``storage = auto`` keeps bricks when they take at most this fraction of the dense bytes
AUTO_SPARSE_FRACTION = 0.5
#: sparse grids up to this many voxels get voxel-exact majorants, as dense ones (built
#: from a dense copy, at most 64 MiB): at 48^3 the brick bounds (6^3 cells) made
#: volpath_delta 1.43x slower on scenes/sparse.xml than the dense grid's 16^3
EXACT_MAJORANT_VOXELS = 256 ** 3


@dataclasses.dataclass
class Bounds:
    """Cell bounds of a store before ``scale``: ``values`` / ``lows`` ``(Rz, Ry, Rx)``,
    the largest value ``grid_max``, over the unit cube of ``to_local``."""
    values: np.ndarray
    lows: np.ndarray
    grid_max: float
    to_local: object


def new_builder(stored_shape, values: GridValues, multiplier, cells: int,
                margin: float = MARGIN):
    """An empty majorant builder for stored grid values of ``stored_shape``: gray bounds
    weighted by the sigma_t multiplier, or, for upsampled RGB (spectral variants), the
    product of the spectrum's and the scale's cell maxima."""
    resolution = resolution_for(stored_shape, cells)
    if values.upsampled:
        return ProductMajorantBuilder(stored_shape, resolution, values.factors,
                                      multiplier.upper, margin)
    return MajorantBuilder(stored_shape, resolution, multiplier.weights(stored_shape[3]),
                           margin)


def built_bounds(builder, to_local) -> Bounds:
    return Bounds(builder.finish(), builder.finish_min(), float(np.float32(builder.max)),
                  to_local)


class DenseStore:
    """The loaded box as one ``Texture3f`` (``data``: its tensor, exposed for editing
    where it holds the file's own values)."""
    kind = "dense"

    def __init__(self, data: mi.TensorXf, values: GridValues, shape, to_local,
                 interpolation: str, builder=None):
        self.data, self.values, self.shape, self.to_local = data, values, shape, to_local
        self.interpolation = interpolation
        self.texture = mi.Texture3f(data, use_accel=True, migrate=True,
                                    filter_mode=INTERPOLATIONS[interpolation],
                                    wrap_mode=dr.WrapMode.Clamp)
        self._loaded = builder      # bounds built while streaming, used once
        self._host = None           # the values of the last edit, read once (changed)

    def eval(self, p: mi.Point3f, wavelengths, active):
        """The value at local point ``p`` as a spectrum."""
        if self.values.upsampled and self.interpolation == "trilinear":
            return self.values.blend(self.texture.eval_fetch(p, active),
                                     cell_position(p, self.shape), wavelengths)
        return self.values.spectrum(self.texture.eval(p, active), wavelengths)

    def bounds(self, multiplier, cells: int, path) -> Bounds:
        builder, self._loaded = self._loaded, None
        if builder is None:       # after an edit: checked (and read) by changed()
            data, self._host = self._host, None
            data = self.data.numpy() if data is None else data
            builder = new_builder(data.shape, self.values, multiplier, cells).add_all(data)
        return built_bounds(builder, self.to_local)

    def traverse(self, callback) -> None:
        if not self.values.converted:
            # differentiable: prbvolpath's gradient w.r.t. it equals the one with
            # heterogeneous + gridvolume (tests/integrators/test_gradients.py). Not exposed where the
            # stored values are not the file's (RGB upsampled in spectral variants,
            # reduced to luminance in mono).
            callback.put("data", self.data, mi.ParamFlags.Differentiable)

    def changed(self, keys=None) -> None:
        previous = self.texture.tensor()
        if tuple(self.data.shape) != tuple(previous.shape):
            shape = tuple(self.data.shape)
            mi.set_property(self.data, mi.TensorXf(previous))
            raise PluginParameterError(
                f"grid_medium: parameter 'data' changed shape from "
                f"{tuple(previous.shape)} to {shape}; allowed: the loaded shape (the "
                "previous values are kept)")
        if not self.values.converted:   # exposed through traverse: may have changed
            self._host = checked_edit("data", self.data.numpy(), lambda: mi.set_property(
                self.data, mi.TensorXf(previous)))
        self.texture.set_tensor(self.data)

    def describe(self) -> str:
        return ""


class SparseStore:
    """Bricks (:class:`~mitsuba_plugins.grids.sparse.SparseGrid`) and their extrema. The stored
    bricks' values are exposed as ``bricks`` (which bricks exist stays fixed)."""
    kind = "sparse"

    def __init__(self, grid, values: GridValues, shape, to_local, interpolation: str,
                 extrema):
        self.grid, self.values, self.shape, self.to_local = grid, values, shape, to_local
        self.interpolation, self.extrema = interpolation, extrema

    def eval(self, p: mi.Point3f, wavelengths, active):
        return grid_value(self.grid, self.values, p, self.interpolation == "trilinear",
                          wavelengths, active)

    def bounds(self, multiplier, cells: int, path) -> Bounds:
        maxima, minima, index = self.extrema
        if int(np.prod(self.shape[:3])) <= EXACT_MAJORANT_VOXELS:
            c = self.grid.channels
            pool = self.grid.pool.numpy().reshape(-1, *(bricks.SIDE,) * 3, c)
            data = bricks.densify(index, pool, (*self.shape[:3], c))
            return built_bounds(new_builder(data.shape, self.values, multiplier, cells).add_all(data),
                          self.to_local)
        # Beyond: the bricks' extrema. At most one cell per brick; 16 by default as for
        # dense storage (on the 1024^3 cloud of benchmarks/sparse_scale.py 64 cells per
        # axis made volpath_delta 1.4x slower: more DDA steps, no fewer collisions).
        rz, ry, rx = (min(cells, c) for c in index.shape)
        z, y, x = self.shape[:3]
        ranges = (voxel_ranges(z, rz), voxel_ranges(y, ry), voxel_ranges(x, rx))
        weights, product = multiplier.weights(self.values.channels), self.values.upsampled
        values, lows = bricks.cell_bounds(maxima, minima, index, self.shape, ranges, weights,
                                          product=product)
        grid_max = np.float32(np.prod(maxima.max(axis=0)) * multiplier.upper if product else
                              (maxima * weights).max())
        return Bounds((values * np.float32(1 + ROUNDING)).astype(np.float32),
                      (lows * np.float32(1 - ROUNDING)).astype(np.float32), float(grid_max),
                      self.to_local)

    def traverse(self, callback) -> None:
        if not self.values.converted:     # as DenseStore: the file's own values only
            callback.put("bricks", self.grid.bricks(), mi.ParamFlags.Differentiable)

    def changed(self, keys=None) -> None:
        if synchronize(self.grid, "bricks", keys):
            self.extrema = (*self.grid.extrema(), self.extrema[2])

    def describe(self) -> str:
        return (f",\n  storage = sparse ({self.grid.stored - 1} bricks stored, "
                f"{self.grid.nbytes / 2**20:.1f} MiB)")


def synchronize(grid, name: str, keys) -> bool:
    """After an edit of a sparse grid's exposed bricks (parameter ``name``): the pool
    re-derived from the owning copies (:meth:`SparseGrid.synchronize`) and every value
    checked (finite, >= 0; otherwise the previous bricks are put back). False where the
    bricks were not exposed or not changed."""
    if not grid.exposed or (keys is not None and name not in keys):
        return False
    previous = mi.Float(grid.pool)
    try:
        grid.synchronize()
    except ValueError as error:
        raise PluginParameterError(f"grid_medium: parameter '{name}' {error}") from None

    def restore():
        grid.pool = previous
        tensor = grid.bricks()
        mi.set_property(tensor, mi.TensorXf(previous, shape=tuple(tensor.shape)))
    checked_edit(name, grid.pool.numpy(), restore)
    return True


def load(header, storage: str, interpolation: str, to_local, multiplier, cells: int):
    """A dense or sparse store of the grid file of ``header`` (``storage`` ``auto``:
    sparse when that takes at most half the dense bytes), every value checked."""
    values = GridValues(header.channels)
    stored = (*header.shape[:3], values.channels)
    if storage == "dense":
        data, builder = _stream_dense(header, values, stored, multiplier, cells)
        return DenseStore(data, values, header.shape, to_local, interpolation, builder)
    from mitsuba_plugins.grids.sparse import SparseGrid
    builder = read_bricks(header, "density", values)
    index = builder.index
    maxima, minima = builder.extrema()
    sparse_bytes = 4 * (index.size + builder.stored * bricks.SIDE ** 3 * stored[3])
    if storage == "auto" and sparse_bytes > AUTO_SPARSE_FRACTION * 4 * np.prod(stored):
        _, pool, _, _ = builder.finish()
        data = bricks.densify(index, pool, stored)
        del pool
        majorants = new_builder(stored, values, multiplier, cells).add_all(data)
        return DenseStore(mi.TensorXf(data), values, header.shape, to_local, interpolation,
                          majorants)
    grid = SparseGrid(stored, index, builder.pool_chunks(), builder.stored)
    return SparseStore(grid, values, header.shape, to_local, interpolation,
                       (maxima, minima, index))


def _stream_dense(header, values: GridValues, stored, multiplier, cells: int):
    """The file streamed slab by slab into one device tensor, and its majorant builder."""
    check_dense_memory(header, stored)
    builder = new_builder(stored, values, multiplier, cells)
    flat = dr.zeros(mi.Float, int(np.prod(stored)))
    slab_elems = int(np.prod(stored[1:]))
    check = ValueCheck(header.path, "density")
    for z0, slab in gridio.iter_slabs(header):
        slab = values.convert(check(slab))
        builder.add(z0, slab)
        flat_slab = slab.reshape(-1)
        for start in range(0, flat_slab.size, UPLOAD_CHUNK):
            chunk = flat_slab[start:start + UPLOAD_CHUNK]
            index = dr.arange(mi.UInt32, z0 * slab_elems + start,
                              z0 * slab_elems + start + chunk.size)
            dr.scatter(flat, mi.Float(chunk), index)
            dr.eval(flat)
    check.report()
    return mi.TensorXf(flat, shape=stored), builder


def read_bricks(header, what: str, values: GridValues,
                lo: float = 0.0) -> bricks.BrickBuilder:
    """A filled :class:`~mitsuba_plugins.grids.bricks.BrickBuilder` of a grid file, every value
    checked (:class:`ValueCheck`: finite, >= ``lo``; ``what`` names the data in errors)
    and stored as ``values`` says (a brick's extrema are then those of the majorant factors of upsampled RGB).
    For a .vdb the OpenVDB worker cuts the bricks and only stored ones cross the pipe (a
    non-finite or negative value is non-zero, so its brick is among the checked ones)."""
    builder = bricks.BrickBuilder((*header.shape[:3], values.channels),
                                  bounds=values.factors if values.upsampled else None)
    check = ValueCheck(header.path, what, lo)
    if header.vdb_grid is not None:
        from mitsuba_plugins.grids.vdb_openvdb import iter_vdb_bricks
        for row, cols, blocks in iter_vdb_bricks(header):
            builder.add_row(row, cols, values.convert(check(blocks)))
    else:
        for z0, slab in gridio.iter_slabs(header):
            builder.add(z0, values.convert(check(slab)))
    builder.finish_check()
    check.report()
    return builder


def load_side_grid(path: str, name: str, to_world: mi.ScalarTransform4f,
                   parameter: str = "emission_grid", channels=(1, 3), lo: float = 0.0):
    """``(SparseGrid, GridValues, world -> local)`` of grid ``name`` of a .vdb (values
    finite and >= ``lo``), the grid that ``grid_medium``'s ``parameter`` names (its
    errors say so), of ``channels`` channels in the file."""
    from mitsuba_plugins.grids.sparse import SparseGrid
    header = gridio.read_header(path, name)
    if header.channels not in channels:
        raise PluginParameterError(
            f"grid_medium: parameter '{parameter}' = {name!r} names a grid of "
            f"{header.channels} channels in '{path}'; allowed: "
            + " or ".join({1: "a float grid", 3: "a vec3 grid"}[c] for c in channels))
    values = GridValues(header.channels)
    builder = read_bricks(header, f"{parameter} {name!r}", values, lo)
    grid = SparseGrid((*header.shape[:3], values.channels), builder.index,
                      builder.pool_chunks(), builder.stored)
    return grid, values, placement.vdb_to_world(header, to_world).inverse()


# -- lookups ---------------------------------------------------------------------------------
def grid_value(grid, values: GridValues, p: mi.Point3f, trilinear: bool, wavelengths,
               active) -> mi.UnpolarizedSpectrum:
    """The value of a sparse grid (:class:`~mitsuba_plugins.grids.sparse.SparseGrid`) at local
    point ``p`` as a spectrum (upsampled RGB: Mitsuba's blend, mitsuba_plugins.grids.spectra)."""
    if values.upsampled:
        if trilinear:
            corners, f = grid.fetch(p, active)
            return values.blend(corners, f, wavelengths)
        return values.spectrum(grid.eval(p, False, active), wavelengths)
    value = grid.eval(p, trilinear, active)
    return mi.UnpolarizedSpectrum(value) if grid.channels == 1 else value


def cell_position(p: mi.Point3f, shape) -> mi.Vector3f:
    """Where local ``p`` lies between the voxel centres that a trilinear texture lookup
    blends (``gridvolume``'s weights for ``Texture3f.eval_fetch``)."""
    z, y, x = shape[:3]
    q = dr.fma(p, mi.Vector3f(x, y, z), -0.5)
    return q - dr.floor(q)


