"""Every bad parameter fails at load with a message naming it and its allowed values."""
import mitsuba as mi
import pytest

BAD = [
    ({"type": "direct_mis", "heuristic": "veach"}, "'heuristic' = 'veach' is invalid; allowed: power | balance | emitter_only | bsdf_only"),
    ({"type": "direct_mis", "emitter_samples": -1}, "'emitter_samples' = -1 is invalid; allowed: an integer in [0, 64]"),
    ({"type": "direct_mis", "bsdf_samples": -3}, "'bsdf_samples' = -3 is invalid"),
    ({"type": "direct_mis", "shading_samples": -1}, "'shading_samples' = -1 is invalid"),
    ({"type": "direct_mis", "emitter_samples": 0, "bsdf_samples": 0}, "must be >= 1"),
    ({"type": "direct_mis", "shading_samples": 2, "bsdf_samples": 1}, "not both"),
    ({"type": "direct_mis", "power_exponent": 0.0}, "'power_exponent' = 0.0 is invalid; allowed: a finite number > 0"),
    ({"type": "direct_mis", "power_exponent": -2.0}, "'power_exponent' = -2.0 is invalid"),
    ({"type": "direct_mis", "emitter_selection": "random"}, "'emitter_selection' = 'random' is invalid; allowed: uniform | power"),
    ({"type": "direct_mis", "emiter_samples": 2}, "unknown parameter 'emiter_samples'; allowed:"),
    ({"type": "path_rr", "rr_depth": 0}, "'rr_depth' = 0 is invalid; allowed: an integer >= 1"),
    ({"type": "path_rr", "rr_depth": -4}, "'rr_depth' = -4 is invalid"),
    ({"type": "path_rr", "max_depth": -2}, "'max_depth' = -2 is invalid; allowed: an integer >= -1"),
    ({"type": "path_rr", "max_depth": 2.5}, "'max_depth' = 2.5 is invalid"),
    ({"type": "path_rr", "rr_rule": "always"}, "'rr_rule' = 'always' is invalid; allowed: throughput | fixed"),
    ({"type": "path_rr", "rr_survival": 0.0}, "'rr_survival' = 0.0 is invalid; allowed: a finite number > 0 and <= 1"),
    ({"type": "path_rr", "rr_survival": 1.5}, "'rr_survival' = 1.5 is invalid"),
    ({"type": "path_rr", "rr_min_survival": 0.99}, "'rr_min_survival' = 0.99 is invalid; allowed: a finite number >= 0 and <= 0.95"),
    ({"type": "path_rr", "rr_max_survival": 0.5, "rr_min_survival": 0.8}, "'rr_min_survival' = 0.8 is invalid; allowed: a finite number >= 0 and <= 0.5"),
    ({"type": "path_rr", "rr_max_survival": 0.0}, "'rr_max_survival' = 0.0 is invalid; allowed: a finite number > 0 and <= 0.9999"),
    ({"type": "volpath_delta", "rr_max_survival": 1.0}, "'rr_max_survival' = 1.0 is invalid; allowed: a finite number > 0 and <= 0.9999"),
    ({"type": "volpath_delta", "transmittance": "kettunen"}, "'transmittance' = 'kettunen' is invalid; allowed: ratio | residual | track_length"),
    ({"type": "path_rr", "max_dpeth": 3}, "unknown parameter 'max_dpeth'; allowed: hide_emitters"),
    ({"type": "path_rr", "hide_emitters": True, "samples": 4}, "unknown parameter 'samples'"),
]


@pytest.mark.parametrize("props, message", BAD, ids=[f"{d['type']}-{m[:30]}" for d, m in BAD])
def test_rejected_at_load(props, message):
    with pytest.raises(RuntimeError) as err:
        mi.load_dict(props)
    assert message in str(err.value)
    assert f"{props['type']}:" in str(err.value)  # names the plugin


def test_defaults_and_to_string():
    integ = mi.load_dict({"type": "direct_mis"})
    assert "emitter_samples = 1" in integ.to_string() and "power (exponent 2)" in integ.to_string()
    integ = mi.load_dict({"type": "path_rr", "max_depth": 7, "rr_rule": "fixed", "rr_survival": 0.8})
    assert "max_depth = 7" in integ.to_string() and "fixed (survival 0.8" in integ.to_string()
