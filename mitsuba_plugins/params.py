"""Parse and validate plugin parameters with Mitsuba's names, failing with a message
that names the parameter and the allowed values."""
from __future__ import annotations

import math

#: Parameters that Mitsuba's SamplingIntegrator base class reads itself.
SAMPLING_INTEGRATOR_BASE = ("hide_emitters", "samples_per_pass", "timeout")


class PluginParameterError(ValueError):
    """A plugin parameter is unknown, of the wrong type or out of range."""


class Params:
    """Typed access to a ``mi.Properties`` for plugin ``plugin``.

    Construction rejects names outside ``allowed`` (a misspelled parameter is an error,
    not a silent default); nested objects of a type in ``objects`` (e.g. a medium's
    ``<phase>``, whose name Mitsuba generates) are let through under any name.
    """

    def __init__(self, props, plugin: str, allowed, objects: tuple = ()):
        self.props = props
        self.plugin = plugin
        self.allowed = tuple(allowed)
        unknown = [k for k in props.keys() if k not in self.allowed
                   and not (objects and isinstance(props[k], objects))]
        if unknown:
            raise PluginParameterError(
                f"{plugin}: unknown parameter{'s' if len(unknown) > 1 else ''} "
                f"{', '.join(repr(k) for k in unknown)}; allowed: {', '.join(self.allowed)}")

    def has(self, name: str) -> bool:
        return name in self.props

    def _fail(self, name, value, allowed: str):
        raise PluginParameterError(f"{self.plugin}: parameter '{name}' = {value!r} is invalid; "
                                   f"allowed: {allowed}")

    def _get(self, name, default):
        return self.props.get(name, default) if self.has(name) else default

    def int(self, name: str, default: int, lo: int | None = None, hi: int | None = None) -> int:
        value = self._get(name, default)
        rng = _range_text(lo, hi, "integer")
        if isinstance(value, bool) or not isinstance(value, int):
            self._fail(name, value, rng)
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            self._fail(name, value, rng)
        return value

    def float(self, name: str, default: float, lo: float | None = None,
              hi: float | None = None, lo_open: bool = False) -> float:
        value = self._get(name, default)
        lo_text = None if lo is None else (f"> {lo:g}" if lo_open else f">= {lo:g}")
        rng = " and ".join(t for t in (lo_text, None if hi is None else f"<= {hi:g}") if t) or "any"
        rng = f"a finite number {rng}" if rng != "any" else "a finite number"
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self._fail(name, value, rng)
        if lo is not None and (value < lo or (lo_open and value == lo)):
            self._fail(name, value, rng)
        if hi is not None and value > hi:
            self._fail(name, value, rng)
        return float(value)

    def choice(self, name: str, default: str, choices) -> str:
        value = self._get(name, default)
        if value not in choices:
            self._fail(name, value, " | ".join(choices))
        return value

    def bool(self, name: str, default: bool) -> bool:
        value = self._get(name, default)
        if not isinstance(value, bool):
            self._fail(name, value, "true | false")
        return value

    def color(self, name: str, default: float, what: str = "a float or rgb") -> list:
        """A non-negative float or rgb parameter as three floats."""
        import mitsuba as mi
        value = self.props[name] if self.has(name) else default
        if isinstance(value, mi.Object):
            raise PluginParameterError(
                f"{self.plugin}: parameter '{name}' must be {what} (got a "
                f"{value.class_name()})")
        try:
            values = floats(value)
        except (TypeError, ValueError):
            raise PluginParameterError(
                f"{self.plugin}: parameter '{name}' = {value!r} is invalid; allowed: a float "
                "or rgb >= 0") from None
        values = values * 3 if len(values) == 1 else values
        if len(values) != 3 or not all(math.isfinite(v) and v >= 0 for v in values):
            raise PluginParameterError(
                f"{self.plugin}: parameter '{name}' = {values} is invalid; allowed: finite "
                "values >= 0")
        return values

    def volume(self, name: str, default, hi: float | None = None, illuminant: bool = False):
        """A float, rgb or nested volume parameter as a ``mi.Volume`` (a constant
        range-checked here; check a nested volume's values with
        :func:`mitsuba_plugins.grids.nested_volume.check_volume_range`).

        In spectral variants a constant is upsampled by Mitsuba's rules: ``illuminant``
        (emission) as an emitter's radiance is (``d65``: an RGB white renders white, as an
        area light of the same value does), otherwise as a reflectance (``rgb``: values in
        [0, 1], as ``homogeneous`` requires of its ``sigma_t``)."""
        import mitsuba as mi
        value = self.props[name] if self.has(name) else default
        if isinstance(value, mi.Volume):
            return value
        values = self.color(name, default, "a float, rgb or volume")
        if hi is not None and max(values) > hi:
            raise PluginParameterError(
                f"{self.plugin}: parameter '{name}' = {values} is invalid; allowed: values "
                f"in [0, {hi:g}]")
        if illuminant and mi.is_spectral:
            spec = {"type": "d65", "color": values}
        elif len(set(values)) == 1:
            spec = values[0]
        else:
            if mi.is_spectral and max(values) > 1:
                raise PluginParameterError(
                    f"{self.plugin}: parameter '{name}' = {values} is invalid in the spectral "
                    f"variant '{mi.variant()}'; allowed: rgb values in [0, 1] (upsampled as a "
                    "reflectance, as for Mitsuba's media): divide them by their maximum and "
                    "multiply 'scale' by it")
            spec = {"type": "rgb", "value": values}
        return mi.load_dict({"type": "constvolume", "value": spec})

    def max_depth(self, default: int = -1) -> int:
        """Mitsuba's ``max_depth``: -1 = unbounded, else the longest path depth (>= 0)."""
        return self.int("max_depth", default, lo=-1)

    def rr_depth(self, default: int = 5) -> int:
        return self.int("rr_depth", default, lo=1)


def _range_text(lo, hi, kind):
    if lo is not None and hi is not None:
        return f"an {kind} in [{lo}, {hi}]"
    if lo is not None:
        return f"an {kind} >= {lo}"
    if hi is not None:
        return f"an {kind} <= {hi}"
    return f"an {kind}"


def depth_limit(max_depth: int) -> int:
    """``max_depth`` as the unsigned bound Mitsuba compares against (-1 -> 2^32 - 1)."""
    return 0xFFFFFFFF if max_depth < 0 else max_depth


def floats(value) -> list:
    """Python floats of a scalar, Color or Dr.Jit array of width 1."""
    import numpy as np
    if isinstance(value, (int, float)):
        return [float(value)]
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    return [float(v) for v in arr]

