"""The comparison CLI: both modes, its outputs, the reference cache and its key."""
import json
import math
from pathlib import Path

import numpy as np
import pytest

from mitsuba_plugins.tools import cli, report, stats
from mitsuba_plugins.tools.compare import compare, reference_floor
from mitsuba_plugins.tools.scenes import scene_digest

SCENE = "scenes/cornell_box.xml"
PAIR = [{"type": "direct_mis"}, {"type": "direct"}]


@pytest.fixture(scope="module")
def equal_time(tmp_path_factory):
    cache = tmp_path_factory.mktemp("refs")
    return compare(SCENE, PAIR, time_budget=0.3, spp_per_pass=4, ref_spp=4096, res=16,
                   cache_dir=cache, progress=False), cache


def test_equal_time_spends_each_budget(equal_time):
    result, _ = equal_time
    assert result.mode == "equal-time"
    for row in result.rows:
        # passes stop as soon as the budget is spent: over it by less than one pass
        last_pass = row.curve_seconds[-1] - (row.curve_seconds[-2] if row.passes > 1 else 0)
        assert 0.3 <= row.seconds < 0.3 + last_pass + 1e-9
        assert row.spp == 4 * row.passes == 4 * len(row.curve_rel_mse)
        assert np.all(np.diff(row.curve_seconds) > 0)
        assert row.invalid == 0
    ours, builtin = result.rows
    assert ours.builtin is False and builtin.builtin is True
    assert math.isclose(ours.efficiency_ratio, ours.efficiency / builtin.efficiency)
    assert math.isnan(builtin.efficiency_ratio)


def test_rel_mse_subtracts_the_reference_noise(equal_time):
    result, _ = equal_time
    floor = reference_floor(result.references["direct"])
    for row in result.rows:
        measured = stats.rel_mse(row.image, result.references["direct"].mean)
        assert math.isclose(row.rel_mse_measured, measured, rel_tol=1e-9)
        assert math.isclose(row.rel_mse, measured - floor, rel_tol=1e-9)


def test_equal_spp_and_cache(equal_time, tmp_path):
    _, cache = equal_time
    before = sorted(p.name for p in cache.iterdir())
    result = compare(SCENE, PAIR, spp=8, passes=2, ref_spp=4096, res=16, cache_dir=cache,
                     progress=False)
    assert sorted(p.name for p in cache.iterdir()) == before  # the reference was reused
    assert any(n.endswith("_se.exr") for n in before) and any(n.endswith(".npz") for n in before)
    assert [r.spp for r in result.rows] == [8, 8] and [r.passes for r in result.rows] == [2, 2]


def test_outputs(equal_time, tmp_path):
    result, _ = equal_time
    paths = report.write_all(result, tmp_path)
    for p in (*paths["tables"], *paths["images"], paths["curves"], paths["panel"]):
        assert p.is_file() and p.stat().st_size > 0, p
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["mode"] == "equal-time" and len(data["rows"]) == 2
    assert data["rows"][0]["curve_rel_mse"] == result.rows[0].curve_rel_mse
    csv_lines = (tmp_path / "table.csv").read_text().splitlines()
    assert len(csv_lines) == 3 and csv_lines[0].startswith("integrator,reference")
    md = (tmp_path / "table.md").read_text()
    assert md.startswith("| integrator |") and "eff. / built-in" in md


def test_scene_digest_follows_referenced_files(tmp_path):
    grid = tmp_path / "g.npy"
    np.save(grid, np.ones((2, 2, 2), np.float32))
    xml = tmp_path / "s.xml"
    xml.write_text('<scene version="3.0.0"><medium type="grid_medium" id="m">'
                   '<string name="filename" value="g.npy"/></medium></scene>')
    first = scene_digest(str(xml))
    np.save(grid, 2 * np.ones((2, 2, 2), np.float32))
    assert scene_digest(str(xml)) != first


def test_cli_equal_time(tmp_path, capsys):
    rc = cli.main(["compare", SCENE, "-i", "path_rr:max_depth=3,path:max_depth=3", "--res", "16",
                   "--time-budget", "0.2", "--spp-per-pass", "4", "--ref-spp", "64",
                   "--cache", str(tmp_path / "refs"), "-o", str(tmp_path / "out"), "-q"])
    text = capsys.readouterr().out
    assert rc == 0
    assert "NaN/Inf samples: 0" in text and "path_rr:max_depth=3" in text
    assert (tmp_path / "out" / "panel.png").is_file()
    page = tmp_path / "out" / "report.html"
    assert f"report (open in a browser, works offline): {page}" in text and page.is_file()


@pytest.mark.parametrize("args, message", [
    (["--time-budget", "0"], "--time-budget = 0.0 is invalid; allowed: a number of seconds in"),
    (["--time-budget", "1e300"], "allowed: a number of seconds in (0, 604800]"),  # years
    (["-i", "direct_mis,direct,direct_mis"], "-i lists 'direct_mis' more than once"),
    (["--spp", "2", "--passes", "4"], "--spp (2) must be >= --passes (4)"),
    (["--spp-per-pass", "0", "--time-budget", "1"], "--spp-per-pass = 0 is invalid; allowed: an integer >= 1"),
    (["--ref-spp", "8"], "--ref-spp must be >= 16"),
    (["--time-budget", "nan"], "--time-budget = nan is invalid"),
    (["--time-budget", "inf"], "--time-budget = inf is invalid"),   # would never end
    (["--res", "0"], "--res = 0 is invalid; allowed: an integer in [1, 16384]"),
    (["--seed", "-1"], "--seed = -1 is invalid; allowed: an integer in [0, 4294967295]"),
])
def test_cli_rejects_bad_options(args, message, capsys, tmp_path):
    integrators = [] if "-i" in args else ["-i", "path_rr"]
    assert cli.main(["compare", SCENE, *integrators, "--res", "8", "--cache", str(tmp_path),
                     *args]) == 2
    assert message in capsys.readouterr().err


def test_a_black_reference_is_an_error_not_an_infinite_efficiency(tmp_path, capsys):
    """A scene without emitters renders black: relative MSE 0 and efficiency inf were
    reported without a word."""
    scene = tmp_path / "dark.xml"
    scene.write_text("""<scene version="3.0.0">
        <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>
            <integer name="height" value="8"/></film></sensor>
        <shape type="sphere"><bsdf type="diffuse"/></shape></scene>""")
    assert cli.main(["compare", str(scene), "-i", "path_rr,path", "--spp", "4", "--passes",
                     "2", "--ref-spp", "16", "-q", "--cache", str(tmp_path / "c"),
                     "-o", str(tmp_path / "o")]) == 2
    assert "reference image (path) is black: the scene has no emitter" in \
        capsys.readouterr().err


def test_reference_override(tmp_path):
    """--reference measures every integrator against one integrator (e.g. volpath_delta
    where volpath is biased); ratios stay to the built-in row."""
    result = compare(SCENE, [{"type": "path_rr", "max_depth": 3}, {"type": "path", "max_depth": 3}],
                     spp=8, passes=2, ref_spp=256, res=16, cache_dir=tmp_path, progress=False,
                     reference={"type": "path_rr", "max_depth": 3})
    assert [r.reference for r in result.rows] == ["path_rr:max_depth=3"] * 2
    assert list(result.references) == ["path_rr:max_depth=3"]
    assert not np.isnan(result.rows[0].efficiency_ratio)


def test_ours_or_builtin_comes_from_the_registry():
    """Issue 14.6: a Mitsuba integrator absent from integrator_specs.BUILTIN (volpathmis, ptracer)
    is a built-in, every registered plugin is ours, and every key of BUILTIN is one."""
    from mitsuba_plugins.tools import integrator_specs
    from mitsuba_plugins.registry import PLUGINS
    assert all(integrator_specs.is_ours(name) for name in PLUGINS)
    assert not any(integrator_specs.is_ours(name) for name in ("volpathmis", "ptracer", "path", "prb"))
    assert set(integrator_specs.BUILTIN) <= set(PLUGINS)


FIRE = str(Path(__file__).resolve().parents[2] / "scenes" / "fire.xml")


def test_emissive_media_are_measured_against_a_reference_that_renders_them(tmp_path):
    """Issue 46.3: on scenes/fire.xml volpath (no medium emission) was the reference:
    volpath_delta got rel. MSE 0.366 and "eff. / built-in 0.003" without a word. The
    reference now renders the emission, volpath's row says what it ignores, and no ratio
    is taken to it."""
    result = compare(FIRE, [{"type": "volpath_delta", "max_depth": 4},
                            {"type": "volpath", "max_depth": 4}],
                     spp=4, passes=2, ref_spp=64, res=12, cache_dir=tmp_path, progress=False)
    ours, builtin = result.rows
    assert ours.reference == builtin.reference == "volpath_delta:max_depth=4"
    assert (ours.ignores, builtin.ignores) == ("", "medium emission")
    assert math.isnan(ours.efficiency_ratio) and math.isnan(ours.rel_mse_ratio)
    text = report.table(result) + report.legend(result)
    assert "medium emission" in text and "WARNING: volpath:max_depth=4 ignores" in text


def test_a_reference_that_ignores_part_of_the_scene_is_refused(tmp_path, capsys):
    assert cli.main(["compare", FIRE, "-i", "volpath_delta", "--reference", "volpath",
                     "--res", "8", "--cache", str(tmp_path), "-q"]) == 2
    assert ("--reference volpath ignores the medium emission of" in capsys.readouterr().err)


@pytest.mark.parametrize("integrator, part", [("volpath", "medium emission"),
                                              ("path_rr", "participating media"),
                                              ("direct_mis", "participating media")])
def test_render_warns_when_the_integrator_ignores_part_of_the_scene(tmp_path, capsys,
                                                                    integrator, part):
    assert cli.main(["render", FIRE, "-i", f"{integrator}", "--spp", "1", "--res", "4",
                     "-o", str(tmp_path / "f.exr")]) == 0
    assert f"warning: this integrator ignores the {part} of" in capsys.readouterr().err


def test_compare_never_overwrites_files_it_did_not_write(equal_time, tmp_path, capsys):
    """Issue 46: ``compare -o DIR`` into a folder of the user's overwrote their own
    ``table.md`` / ``panel.png``. Refused before any rendering; a folder an earlier
    compare wrote is rewritten."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "table.md").write_text("my notes")
    rc = cli.main(["compare", SCENE, "-i", "path_rr", "--res", "8", "--spp", "2",
                   "--passes", "1", "--cache", str(tmp_path / "c"), "-o", str(out), "-q"])
    assert rc == 2
    assert (f"-o/--output '{out}' holds table.md that compare did not write"
            in capsys.readouterr().err)
    assert (out / "table.md").read_text() == "my notes"
    fresh = tmp_path / "fresh"
    report.write_all(equal_time[0], fresh)
    report.write_all(equal_time[0], fresh)        # its own files: rewritten
    assert report.written_by_compare(fresh)


def test_compare_writes_every_file_or_none(equal_time, tmp_path, monkeypatch):
    """A write that fails half-way (a full disk) left table.md written and the rest not,
    then said "nothing was written": now none of the set lands, and the message says so."""
    from mitsuba_plugins import output
    out = tmp_path / "out"

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(report, "plot_panel", full_disk)
    with pytest.raises(OSError, match="No space left on device"):
        report.write_all(equal_time[0], out)
    assert not out.exists() or not any(out.iterdir()), list(out.iterdir())
    monkeypatch.undo()
    with pytest.raises(output.OutputError, match="none of this command's files was written"):
        with output.all_or_nothing():
            output.write_text(tmp_path / "a.md", "a")
            with output.atomic_path(tmp_path / "b.md") as tmp:
                Path(tmp).write_text("half")
                raise RuntimeError("disk full")
    assert not (tmp_path / "a.md").exists() and not list(tmp_path.glob(".*tmp*"))


def test_reference_floor_removes_the_references_own_noise():
    """An image of relative variance 1e-3 per pixel against a reference averaged from 32
    renders of relative variance 0.02 each (its mean's: 6.25e-4). The raw relMSE carries
    the reference's noise (+62%); less ``reference_floor`` it is the image's own. Tolerance:
    5 standard errors of the mean over 10^5 pixels (a pixel's squared error is a scaled
    chi-square of one degree: standard deviation sqrt(2) (1e-3 + 6.25e-4)), 3.6e-5,
    against a floor of 6.25e-4."""
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.5, 2.0, 100_000)
    ref = stats.Estimate.from_passes(
        truth * (1 + math.sqrt(0.02) * rng.standard_normal((32, truth.size))), 256)
    image = truth * (1 + math.sqrt(1e-3) * rng.standard_normal(truth.size))
    want = float(np.mean(1e-3 * truth ** 2 / (truth ** 2 + stats.REL_MSE_EPS)))
    raw = stats.rel_mse(image, ref.mean)
    tol = 5 * math.sqrt(2) * (1e-3 + 6.25e-4) / math.sqrt(truth.size)
    assert abs(raw - reference_floor(ref) - want) < tol, (raw, reference_floor(ref), want)
    assert raw - want > 10 * tol          # uncorrected, the test above would fail
