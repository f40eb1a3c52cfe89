"""MIS heuristics alone (ALGORITHMS.md section 2)."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mitsuba_plugins import mis

A = [0.0, 0.5, 1.0, 3.0, 1e-8, 7.0]
B = [2.0, 0.5, 0.0, 1.0, 5.0, 0.0]


def arr(x):
    return mi.Float(x)


@pytest.mark.parametrize("heuristic", ["power", "balance", "emitter_only", "bsdf_only"])
def test_weights_sum_to_one_where_either_density_is_positive(heuristic):
    m = mis.MIS(heuristic, 2.0)
    w_l = m.weight(arr(A), arr(B), emitter_technique=True)
    w_b = m.weight(arr(B), arr(A), emitter_technique=False)
    assert np.allclose(np.array(w_l + w_b), 1.0, atol=1e-6)


def test_weight_is_zero_where_own_density_is_zero():
    for h in ("power", "balance", "emitter_only"):
        w = mis.MIS(h).weight(arr([0.0, 0.0]), arr([1.0, 0.0]), emitter_technique=True)
        assert np.all(np.array(w) == 0.0), h


def test_values():
    assert np.allclose(np.array(mis.balance_heuristic(arr([1.0]), arr([3.0]))), 0.25)
    assert np.allclose(np.array(mis.power_heuristic(arr([1.0]), arr([3.0]))), 0.1)
    assert np.allclose(np.array(mis.power_heuristic(arr([1.0]), arr([3.0]), 3.0)), 1 / 28)
    assert np.allclose(np.array(mis.power_heuristic(arr([1.0]), arr([3.0]), 1.0)), 0.25)


def test_non_finite_gives_zero():
    w = mis.power_heuristic(arr([0.0, dr.inf]), arr([0.0, dr.inf]))
    assert np.all(np.array(w) == 0.0)


def test_single_technique_rules():
    w = mis.MIS("emitter_only").weight(arr([1.0, 1.0]), arr([0.0, 2.0]), emitter_technique=False)
    assert np.array(w).tolist() == [1.0, 0.0]  # BSDF covers only what emitters cannot reach


def test_bad_configuration():
    with pytest.raises(ValueError, match="heuristic must be one of power, balance"):
        mis.MIS("veach")
    with pytest.raises(ValueError, match="power_exponent must be > 0"):
        mis.MIS("power", 0.0)
