"""Error falls as 1/spp, and MIS beats both single techniques on the Veach scene."""
import numpy as np
import pytest

from helpers import load, render
from mitsuba_plugins.tools import stats


@pytest.mark.parametrize("integrator, builtin", [({"type": "direct_mis"}, {"type": "direct"}),
                                                 ({"type": "path_rr", "max_depth": 5}, {"type": "path", "max_depth": 5})])
def test_rel_mse_quarters_when_spp_quadruples(integrator, builtin):
    """relMSE(4N) / relMSE(N) = 1/4 for an unbiased estimator. Averaged over 4 seeds;
    accepted in [0.18, 0.33] (the reference, at 64x the spp, adds < 2%)."""
    s = load("cornell_box", res=48)
    ref = render(s, builtin, 4096, seed=99)
    n = 16
    low = np.mean([stats.rel_mse(render(s, integrator, n, k), ref) for k in range(4)])
    high = np.mean([stats.rel_mse(render(s, integrator, 4 * n, 10 + k), ref) for k in range(4)])
    assert 0.18 < high / low < 0.33, f"ratio {high / low:.3f}"


def test_mis_beats_single_techniques_on_veach():
    s = load("veach_mis", res=64)
    ref = render(s, {"type": "direct"}, 2048, seed=77)
    err = {h: np.mean([stats.rel_mse(render(s, {"type": "direct_mis", "heuristic": h}, 16, k), ref)
                       for k in range(3)])
           for h in ("power", "balance", "emitter_only", "bsdf_only")}
    assert err["power"] < err["emitter_only"] and err["power"] < err["bsdf_only"], err
    assert err["balance"] < err["emitter_only"] and err["balance"] < err["bsdf_only"], err
