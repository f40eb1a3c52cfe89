"""The side grids of a ``.vdb`` beside its density, for ``grid_medium``: ``emission_grid``
(a radiance factor), ``temperature_grid`` (fire: Planck's spectrum at ``(value - offset) x
scale`` kelvin, :mod:`mitsuba_plugins.grids.blackbody`) and ``albedo_grid`` (a colour
factor of the albedo). Each is a sparse grid of its own placement
(:func:`mitsuba_plugins.grids.stores.load_side_grid`)."""
from __future__ import annotations

import mitsuba as mi
import numpy as np

from mitsuba_plugins.grids import blackbody, stores
from mitsuba_plugins.grids.nested_volume import volume_max
from mitsuba_plugins.params import Params, PluginParameterError

#: the parameters that select a side grid (each names a grid of the ``filename`` .vdb)
NAMES = ("emission_grid", "temperature_grid", "albedo_grid")


class SideGrids:
    """A medium's side grids, each None where it is not given: ``emission`` and
    ``albedo`` as ``(SparseGrid, GridValues, to_local)``, ``temperature`` as
    ``(SparseGrid, to_local, offset, scale)``."""

    def __init__(self):
        self.emission = self.temperature = self.albedo = None

    def load(self, p: Params, filename: str, to_world: mi.ScalarTransform4f, emission):
        """Loads the side grids ``p`` names from ``filename``; returns the medium's
        ``emission`` volume (made, as Mitsuba's default of 1, where a grid needs one)."""
        if p.has("emission_grid"):
            if emission is None:
                emission = p.volume("emission", 1.0, illuminant=True)
            self.emission = stores.load_side_grid(filename, p.props["emission_grid"], to_world)
        emission = self._load_temperature(p, filename, to_world, emission)
        if p.has("albedo_grid"):
            self.albedo = stores.load_side_grid(filename, p.props["albedo_grid"], to_world,
                                                "albedo_grid")
        return emission

    def _load_temperature(self, p: Params, filename: str, to_world, emission):
        """``temperature_grid`` and its offset and scale (fire, :mod:`blackbody`)."""
        offset = p.float("temperature_offset", 0.0)
        scale = p.float("temperature_scale", 1.0, lo=0.0, lo_open=True)
        if not p.has("temperature_grid"):
            for name in ("temperature_offset", "temperature_scale"):
                if p.has(name):
                    raise PluginParameterError(
                        f"grid_medium: parameter '{name}' applies to a 'temperature_grid'; "
                        "give one (the name of a float grid of the .vdb, e.g. 'temperature')")
            return emission
        name = p.props["temperature_grid"]
        if p.has("emission_grid"):
            raise PluginParameterError(
                "grid_medium: parameters 'temperature_grid' and 'emission_grid' both set the "
                "emitted radiance; give one of them")
        if scale <= 0.0:
            raise PluginParameterError(
                f"grid_medium: parameter 'temperature_scale' = {scale:g} is out of range; "
                "allowed: > 0 (kelvin per unit of the grid)")
        if emission is None:
            emission = p.volume("emission", 1.0)
        # any finite value: T = (value - offset) x scale, and a voxel at or below 0 K
        # emits nothing (a negative grid made positive by the offset was refused)
        grid, _, to_local = stores.load_side_grid(filename, name, to_world,
                                                  "temperature_grid", channels=(1,),
                                                  lo=-np.inf)
        hottest = (float(grid.extrema()[0].max(initial=0.0)) - offset) * scale
        if hottest > blackbody.T_MAX:
            raise PluginParameterError(
                f"grid_medium: temperature_grid {name!r} of '{filename}' reaches "
                f"{hottest:.4g} K with temperature_offset = {offset:g} and temperature_scale "
                f"= {scale:g}; allowed: at most {blackbody.T_MAX:g} K (check the grid's "
                "units and temperature_scale)")
        self.temperature = (grid, to_local, offset, scale)
        return emission

    def check_albedo(self, albedo: mi.Volume) -> None:
        """``albedo`` x ``albedo_grid`` within [0, 1] (the grid's values are >= 0)."""
        if self.albedo is None:
            return
        grid, values, _ = self.albedo
        pool = grid.pool.numpy().reshape(-1, values.channels)
        if values.upsampled:      # scale x model spectrum: bounded by their maxima
            upper, _ = values.factors(pool)
            top = float((upper[:, 0] * upper[:, 1]).max(initial=0.0))
        else:
            top = float(pool.max(initial=0.0))
        highest = top * volume_max(albedo, slack=0.0)
        if highest > 1.0 + 1e-6:
            raise PluginParameterError(
                f"grid_medium: parameters 'albedo' x 'albedo_grid' reach {highest:.4g}; "
                "allowed: albedo values in [0, 1] (scale the grid or set 'albedo')")

    @staticmethod
    def value(side, mei: mi.MediumInteraction3f, trilinear: bool, active):
        """The value of a side grid ``(SparseGrid, GridValues, to_local)`` at ``mei.p``
        as a spectrum (``emission``, ``albedo``)."""
        grid, values, to_local = side
        return stores.grid_value(grid, values, mi.Transform4f(to_local) @ mei.p, trilinear,
                                 mei.wavelengths, active)

    def radiance(self, radiance, mei: mi.MediumInteraction3f, trilinear: bool, active):
        """``radiance`` (the ``emission`` volume's value) times the emission grid and
        Planck's spectrum at the temperature grid's value, where they are given."""
        if self.emission is not None:
            radiance *= self.value(self.emission, mei, trilinear, active)
        if self.temperature is not None:
            grid, to_local, offset, scale = self.temperature
            value = grid.eval(mi.Transform4f(to_local) @ mei.p, trilinear, active)
            radiance *= blackbody.spectrum((value - offset) * scale, mei.wavelengths, active)
        return radiance

    def traverse(self, callback) -> None:
        """The bricks of the emission and albedo grids (where they are not converted)."""
        for side, key in ((self.emission, "emission_bricks"), (self.albedo, "albedo_bricks")):
            if side is not None and not side[1].converted:
                callback.put(key, side[0].bricks(), mi.ParamFlags.Differentiable)

    def changed(self, keys, albedo: mi.Volume) -> None:
        """After a parameter edit: edited bricks synchronised and checked, and the
        albedo product checked again where an albedo changed."""
        if self.emission is not None:
            stores.synchronize(self.emission[0], "emission_bricks", keys)
        if self.albedo is not None:
            stores.synchronize(self.albedo[0], "albedo_bricks", keys)
            if keys is None or any(k.startswith("albedo") for k in keys):
                self.check_albedo(albedo)
