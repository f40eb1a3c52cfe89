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
