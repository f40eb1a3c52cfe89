"""Multiple-importance-sampling weights (Veach 1997, ch. 9; docs/method.md section 2).

Every function takes the *effective* densities ``a = n_self * p_self`` and
``b = n_other * p_other`` of two techniques, both in the same measure (solid angle), and
returns the weight of the technique that drew the sample. A non-finite ratio (both
densities zero or infinite) yields weight 0, as in Mitsuba.
"""
from __future__ import annotations

import drjit as dr

HEURISTICS = ("power", "balance", "emitter_only", "bsdf_only")


def _finite_or_zero(w):
    return dr.select(dr.isfinite(w), w, 0.0)


def balance_heuristic(a, b):
    """w = a / (a + b): optimal for one-sample MIS."""
    return _finite_or_zero(a / (a + b))


def power_heuristic(a, b, exponent: float = 2.0):
    """w = a^e / (a^e + b^e). ``exponent == 2`` uses the same operations as Mitsuba's
    C++ ``mis_weight`` so that ports stay bit-identical.

    Any other exponent is computed from the ratio of the smaller density to the larger,
    ``r = min / max`` in [0, 1]: ``w = 1 / (1 + r^e)`` for the larger technique and
    ``r^e / (1 + r^e)`` for the smaller. ``r^e`` cannot overflow and underflows to 0
    harmlessly, so the two weights of a sample still sum to 1 for exponents up to 1e6
    and beyond; raising the densities themselves overflows float32 already at e ~ 30
    (``a^e / (a^e + b^e)`` = inf/inf, the sample lost: 31% of a Cornell box at e = 100).
    """
    if exponent == 2.0:
        a2, b2 = dr.square(a), dr.square(b)
        return _finite_or_zero(a2 / (a2 + b2))
    if exponent == 1.0:
        return balance_heuristic(a, b)
    own_larger = a >= b
    r = dr.select(own_larger, b / a, a / b)         # in [0, 1]; NaN when both are 0 or inf
    re = dr.power(r, exponent)
    return _finite_or_zero(dr.select(own_larger, 1.0, re) / (1.0 + re))


def single_technique(a, b, preferred: bool):
    """Weights of a 'use one technique' rule that stays unbiased.

    The preferred technique takes the whole weight wherever it can produce the sample
    (``a > 0``); the other one only covers what the preferred cannot reach (delta BSDF
    lobes for emitter sampling, delta lights for BSDF sampling): weight 1 where the
    preferred density ``b`` is 0.
    """
    if preferred:
        return dr.select(a > 0, 1.0, 0.0)
    return dr.select(b > 0, 0.0, 1.0)


class MIS:
    """A heuristic chosen by name, evaluated for the emitter or the BSDF technique."""

    def __init__(self, heuristic: str = "power", exponent: float = 2.0):
        if heuristic not in HEURISTICS:
            raise ValueError(f"heuristic must be one of {', '.join(HEURISTICS)}; got '{heuristic}'")
        if not exponent > 0:
            raise ValueError(f"power_exponent must be > 0; got {exponent}")
        self.heuristic = heuristic
        self.exponent = float(exponent)

    def weight(self, a, b, emitter_technique: bool):
        """Weight of a sample drawn by the emitter (``emitter_technique``) or BSDF
        technique, with effective densities ``a`` (own) and ``b`` (other)."""
        if self.heuristic == "power":
            return power_heuristic(a, b, self.exponent)
        if self.heuristic == "balance":
            return balance_heuristic(a, b)
        preferred = (self.heuristic == "emitter_only") == emitter_technique
        return single_technique(a, b, preferred)

    def __repr__(self):
        if self.heuristic == "power":
            return f"power (exponent {self.exponent:g})"
        return self.heuristic
