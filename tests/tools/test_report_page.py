"""Issue 28: the metrics beside rel. MSE (MAPE, SMAPE, trimmed rel. MSE, HDR-FLIP, time to
unit variance) and ``report.html``, opened in a real browser (Debian's Chromium, driven by
Playwright; ``bash .ci/setup`` installs both)."""
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from mitsuba_plugins import output
from mitsuba_plugins.tools import metrics, report, stats, viewer
from mitsuba_plugins.tools.compare import Report, Row, compare, reference_floor

SCENE = "scenes/cornell_box.xml"
CHROMIUM = "/usr/bin/chromium"
#: flags for a headless Chromium as root on a machine with no network
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]


# -- metrics ----------------------------------------------------------------------------------
def test_ape_metrics_have_their_stated_values():
    ref = np.array([[[1.0, 0.0, 0.5]]])
    x = np.array([[[1.5, 0.2, 0.5]]])
    assert math.isclose(metrics.mape(x, ref), (0.5 / 1.01 + 0.2 / 0.01 + 0) / 3)
    assert math.isclose(metrics.smape(x, ref), (2 * 0.5 / 2.51 + 2 * 0.2 / 0.21 + 0) / 3)
    assert metrics.mape(ref, ref) == metrics.smape(ref, ref) == 0.0
    assert metrics.smape(np.full((4, 4, 3), 1e6), np.zeros((4, 4, 3))) <= 2.0


def test_trimmed_rel_mse_leaves_out_the_largest_tenth_of_a_percent():
    """Of 4000 pixels, the 4 worst go: fireflies there do not move the trimmed figure, a
    fifth one does; with a noiseless reference the untrimmed one is stats.rel_mse."""
    rng = np.random.default_rng(1)
    mean = rng.uniform(0.5, 1.0, (40, 100, 3))
    ref = stats.Estimate(mean, np.zeros_like(mean), 16, 1)
    image = mean * (1 + 0.01 * rng.standard_normal(mean.shape))
    clean = metrics.rel_mse_trimmed(image, ref)
    fireflies = image.copy()
    hot = [3, 500, 1999, 3999]
    fireflies.reshape(-1, 3)[hot] = 1e4
    others = np.delete(metrics.pixel_rel_se(image, mean).ravel(), hot)
    assert math.isclose(metrics.rel_mse_trimmed(fireflies, ref), others.mean(), rel_tol=1e-12)
    assert math.isclose(others.mean(), clean, rel_tol=0.02)
    fireflies.reshape(-1, 3)[77] = 1e4
    assert metrics.rel_mse_trimmed(fireflies, ref) > 100 * clean
    assert math.isclose(metrics.rel_mse_trimmed(image, ref, share=0.0), stats.rel_mse(image, mean),
                        rel_tol=1e-12)
    assert metrics.kept_pixels(np.zeros((40, 100))).sum() == 3996


def test_trimmed_rel_mse_subtracts_the_reference_noise_it_keeps():
    mean = np.ones((10, 100, 1))
    se = np.full_like(mean, 0.1)
    image = mean.copy()
    value = metrics.rel_mse_trimmed(image, stats.Estimate(mean, se, 16, 1))
    assert math.isclose(value, -0.01 / 1.01, rel_tol=1e-12)


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    """A real comparison, small: four integrators at 32x32, equal spp."""
    cache = tmp_path_factory.mktemp("refs")
    specs = [{"type": "direct_mis"}, {"type": "direct"}, {"type": "path_rr"}, {"type": "path"}]
    result = compare(SCENE, specs, spp=8, passes=2, ref_spp=64, res=32, cache_dir=cache,
                     progress=False)
    out = tmp_path_factory.mktemp("report")
    return result, report.write_all(result, out), out


def test_rows_carry_every_metric_and_its_curve(compared):
    result, _, _ = compared
    for row in result.rows:
        ref = result.references[row.reference]
        expected = metrics.measure(row.image, ref, reference_floor(ref))
        for name in metrics.NAMES:
            assert len(row.curve(name)) == row.passes
            assert math.isclose(row.curve(name)[-1], expected[name], rel_tol=1e-9), name
        assert math.isclose(row.ttuv, row.rel_mse * row.seconds, rel_tol=1e-12)
        assert math.isclose(row.ttuv, 1 / row.efficiency, rel_tol=1e-9)
        assert 0 < row.flip < 1 and 0 < row.mape and 0 < row.smape < 2


def _flip_cli(reference: Path, test: Path, cwd: Path) -> float:
    """NVIDIA's own command-line FLIP (installed with flip-evaluator) on two EXR files."""
    exe = Path(sys.executable).with_name("flip")
    done = subprocess.run([str(exe), "-r", str(reference), "-t", str(test), "-v", "1"],
                          capture_output=True, text=True, cwd=cwd, check=True)
    return float(re.search(r"Mean:\s*([0-9.]+)", done.stdout).group(1))


def test_flip_equals_flip_evaluators_own(compared, tmp_path):
    """Target of issue 28: the FLIP a report shows is what NVIDIA's tool computes from the
    same two images written as EXR (the tool prints 6 decimals).

    The tool reads only RGB files: a mono variant's images are given to it as the gray
    value repeated in three channels, which is what ``metrics.flip`` does with them. In
    spectral variants the images hold negative (out-of-gamut) values, read by both as
    they are."""
    result, _, out = compared
    for row in result.rows:
        ref_exr = _rgb_exr(tmp_path / f"ref_{row.reference}.exr",
                           result.references[row.reference].mean)
        test_exr = out / f"{report.image_name(row.integrator)}.exr"
        if row.image.shape[-1] == 1:
            test_exr = _rgb_exr(tmp_path / test_exr.name, np.array(mi.Bitmap(str(test_exr))))
        assert abs(_flip_cli(ref_exr, test_exr, tmp_path) - row.flip) <= 1.5e-6, row.integrator


def _rgb_exr(path: Path, image: np.ndarray) -> Path:
    """``image`` written as an RGB EXR, as ``metrics.flip`` hands it to FLIP (a gray one
    repeated in three channels)."""
    return output.write_exr(path, metrics._flip_input(image))


# -- the page ---------------------------------------------------------------------------------
def _synthetic_report(size: int, rows: int = 4) -> Report:
    """A report of noisy images of a smooth scene, no rendering: for the page's size."""
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:size, 0:size] / size
    mean = np.stack([0.2 + xx, 0.3 + yy, 0.5 + xx * yy], axis=-1)
    ref = stats.Estimate(mean, np.full_like(mean, 0.01), 16, 64)
    out = []
    for k in range(rows):
        image = mean * (1 + 0.1 * rng.standard_normal(mean.shape))
        m = metrics.measure(image, ref, reference_floor(ref))
        out.append(Row(f"integrator{k}", "direct", 1024, 64, 4, 1.0, m["rel_mse"],
                       m["rel_mse"], 1 / m["rel_mse"], 0, k % 2 == 1,
                       **{k2: v for k2, v in m.items() if k2 != "rel_mse"},
                       curve_seconds=[1.0], **{"curve_" + n: [v] for n, v in m.items()},
                       image=image))
    return Report("synthetic.xml", "equal-spp", out, {"direct": ref}, None, 64)


def test_page_of_a_128_scene_stays_small(tmp_path):
    rep = _synthetic_report(128)
    curves = report.plot_curves(rep, tmp_path / "curves.png")
    page = viewer.write_page(rep, tmp_path / "report.html", report.COLUMNS, report.legend(rep),
                             curves=curves)
    size = page.stat().st_size
    assert size < 3 * 2 ** 20, f"{size / 2 ** 20:.2f} MB"
    text = page.read_text()
    assert "http://" not in text and "https://" not in text   # offline: nothing fetched
    assert "</script" not in text.split('id="report-data">')[1].split("</script>")[0]


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).is_file():
        pytest.fail(f"{CHROMIUM} is missing: the browser test needs Debian's chromium "
                    "(bash .ci/setup installs it)")
    from playwright.sync_api import sync_playwright
    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


@pytest.fixture
def page(browser, compared):
    _, written, _ = compared
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    problems = []
    page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}")
            if m.type in ("error", "warning") else None)
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.on("requestfailed", lambda r: problems.append(f"request failed: {r.url}"))
    page.goto(written["page"].resolve().as_uri())
    page.wait_for_selector("body[data-ready=true]", timeout=20000)
    yield page
    page.close()
    assert problems == []


def _main(page) -> bytes:
    return page.locator("#main").screenshot()


def test_page_opens_and_decodes_every_image(page, compared):
    result = compared[0]
    layers = len(result.references) + len(result.rows)
    assert page.evaluate("window.viewerDecoded") == layers
    # every zoom view holds drawn pixels (not blank canvases)
    drawn = page.evaluate("""() => [...document.querySelectorAll('#zooms canvas')].map(c => {
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let s = 0; for (let i = 0; i < d.length; i += 4) s += d[i] + d[i + 1] + d[i + 2];
        return s; })""")
    assert len(drawn) == layers and all(s > 0 for s in drawn)
    assert page.locator("#curves").evaluate("img => img.complete && img.naturalWidth > 0")


def test_flipping_exposure_and_views_change_what_is_drawn(page, compared):
    result = compared[0]
    page.keyboard.press("1")                                   # the first reference
    reference = _main(page)
    page.keyboard.press(str(len(result.references) + 1))       # the first integrator (8 spp)
    noisy = _main(page)
    assert noisy != reference
    page.keyboard.press("ArrowLeft")
    assert _main(page) != noisy
    page.keyboard.press("ArrowRight")
    assert _main(page) == noisy                                # flipping back: the same image
    page.keyboard.press("+")
    brighter = _main(page)
    assert brighter != noisy
    assert page.evaluate("window.viewerState.exposure") == 0.5
    page.keyboard.press("0")
    assert _main(page) == noisy
    page.keyboard.press("m")
    relerr = _main(page)
    page.keyboard.press("m")
    flip = _main(page)
    assert len({noisy, relerr, flip}) == 3
    # the zoom follows the cursor
    zoom = page.locator("#zooms canvas").first
    before = zoom.screenshot()
    box = page.locator("#main").bounding_box()
    page.mouse.move(box["x"] + 0.1 * box["width"], box["y"] + 0.9 * box["height"])
    assert zoom.screenshot() != before
    assert page.evaluate("[window.viewerState.x, window.viewerState.y]") == [3, 28]


def test_table_matches_the_json(page):
    data = json.loads(page.locator("#report-data").text_content())
    cells = page.evaluate("""() => [...document.querySelectorAll('#metrics tbody tr')].map(
        tr => Object.fromEntries([...tr.querySelectorAll('td')].map(
            td => [td.dataset.key, td.textContent])))""")
    assert len(cells) == len(data["rows"]) == 4
    keys = [attr for _, attr, _ in report.COLUMNS]
    for shown, row in zip(cells, data["rows"]):
        assert list(shown) == keys
        for key in keys:
            value = row[key]
            if value is None:
                assert shown[key] == "-", key
            elif isinstance(value, str):
                assert shown[key] == value, key
            else:   # the page rounds to 4 significant digits or 3 decimals
                assert math.isclose(float(shown[key]), value, rel_tol=5e-4, abs_tol=5e-4), \
                    (key, shown[key], value)

