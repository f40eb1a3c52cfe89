"""Analytic answers (values derived in each scene file's header), one-sample t-tests over
independent pixels at level 1e-3."""
import mitsuba as mi
import numpy as np
import pytest

from helpers import assert_mean_equals, load, render

CLOSED = [  # integrator parameters, expected (Le = 1, albedo 0.5)
    ({"type": "path_rr"}, 2.0),
    ({"type": "path_rr", "rr_depth": 1}, 2.0),
    ({"type": "path_rr", "rr_depth": 1, "rr_rule": "fixed", "rr_survival": 0.5}, 2.0),
    ({"type": "path_rr", "rr_depth": 1, "rr_min_survival": 0.3}, 2.0),
    ({"type": "path_rr", "rr_depth": 1, "rr_max_survival": 0.5}, 2.0),
    ({"type": "path_rr", "max_depth": 3}, 1.75),
    ({"type": "path_rr", "max_depth": 1}, 1.0),
    ({"type": "direct_mis"}, 1.5),
    ({"type": "direct_mis", "heuristic": "balance"}, 1.5),
    ({"type": "direct_mis", "heuristic": "emitter_only"}, 1.5),
    ({"type": "direct_mis", "heuristic": "bsdf_only"}, 1.5),
    ({"type": "direct_mis", "power_exponent": 3.5, "emitter_samples": 3, "bsdf_samples": 1}, 1.5),
]


@pytest.mark.parametrize("integrator, expected", CLOSED, ids=[str(c[0]) for c in CLOSED])
def test_closed_furnace(integrator, expected):
    img = render(load("furnace_closed", res=32), integrator, spp=64, seed=11)
    assert_mean_equals(img, expected, str(integrator))


OPEN = [
    {"type": "path_rr"},
    {"type": "path_rr", "emitter_selection": "power"},
    {"type": "direct_mis"},
    {"type": "direct_mis", "heuristic": "bsdf_only"},
    {"type": "direct_mis", "heuristic": "emitter_only"},
]


@pytest.mark.parametrize("integrator", OPEN, ids=[str(c) for c in OPEN])
def test_open_furnace(integrator):
    img = render(load("furnace_env", res=32), integrator, spp=64, seed=5)
    assert_mean_equals(img, 0.8, str(integrator))


def test_hidden_environment_is_black_and_transparent():
    scene = mi.load_dict({"type": "scene", "env": {"type": "constant"},
                          "sensor": {"type": "perspective",
                                     "film": {"type": "hdrfilm", "width": 4, "height": 4,
                                              "pixel_format": "rgba"}}})
    for name in ("path_rr", "direct_mis"):
        img = render(scene, {"type": name, "hide_emitters": True}, spp=4)
        assert np.all(img == 0), name
