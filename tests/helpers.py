"""Thin glue between the tests and the shared harness in mitsuba_plugins.tools.stats."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins.grids import vdb_openvdb
from mitsuba_plugins.tools import stats
# the small scenes built in code, shared with the benchmarks
from mitsuba_plugins.tools.scenes import (SCENES, SMOKE, SPARSE, camera, grid,  # noqa: F401
                                          homogeneous, media_scene)
from mitsuba_plugins.validity import counted

#: resolution of the media scenes' image tests
RES = 32
FAILURES = Path(os.environ.get("MITSUBA_PLUGINS_TEST_OUT", Path(__file__).resolve().parents[1] / "out" / "test-failures"))


def _default_sigint():
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start_cli(*args, **kw) -> subprocess.Popen:
    """The CLI in a child process (text pipes), with SIGINT at its default disposition:
    a shell starts background jobs with SIGINT ignored and children inherit that (CI run
    as `cmd &` failed the interrupt tests so), so give it what a terminal would."""
    return subprocess.Popen([sys.executable, "-m", "mitsuba_plugins.tools.cli", *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_default_sigint, **kw)


def load(scene: str, **params) -> mi.Scene:
    return mi.load_file(str(SCENES / f"{scene}.xml"), **{k: str(v) for k, v in params.items()})


def estimate(scene, integrator: dict, passes: int, spp: int, seed: int) -> stats.Estimate:
    est = stats.render_passes(scene, passes, spp, integrator=mi.load_dict(integrator),
                              seed=seed, warmup=False)
    assert est.invalid == 0, f"{integrator}: {est.invalid} NaN/Inf samples"
    return est


#: estimates rendered in this test run (see :func:`cached_estimate`)
_ESTIMATES: dict = {}


def cached_estimate(key: str, scene, integrator: dict, passes: int, spp: int,
                    seed: int = 0) -> stats.Estimate:
    """:func:`estimate`, rendered once per test run for each ``key`` (the scene's
    description: equal keys must mean equal scenes, e.g. ``load:smoke:32``), variant,
    integrator, passes, spp and seed, however many tests use it (a reference most often).
    ``scene``: the scene, or a function that makes it (called only when rendering).
    Callers must not modify what it returns."""
    k = (mi.variant(), key, json.dumps(integrator, sort_keys=True), passes, spp, seed)
    if k not in _ESTIMATES:
        _ESTIMATES[k] = estimate(scene() if callable(scene) else scene, integrator, passes,
                                 spp, seed)
    return _ESTIMATES[k]


def loaded(name: str, res: int = RES):
    """``(key, scene function)`` of a scene file of scenes/ at ``res`` (for
    :func:`cached_estimate`)."""
    return f"load:{name}:{res}", lambda: load(name, res=res)


def render(scene, integrator=None, spp: int = 0, seed: int = 0) -> np.ndarray:
    """``mi.render`` as a float64 array, asserting zero NaN/Inf samples (counted in the
    kernel: ours by their sample guard, Mitsuba's through a counting wrapper) and finite
    pixels. ``integrator``: a plugin dict, an instance, or None (the scene's)."""
    if isinstance(integrator, dict):
        integrator = mi.load_dict(integrator)
    integrator = counted(integrator if integrator is not None else scene.integrator())
    _, img, invalid = stats.timed_pass(scene, integrator, spp, seed)
    assert invalid == 0, f"{integrator}: {invalid} NaN/Inf samples or non-finite pixels"
    return img


def assert_same_render(a: np.ndarray, b: np.ndarray, rtol: float = 1e-5):
    """Two renders of the same random numbers agree up to float rounding. Not bit for
    bit: the film adds a pixel's samples with atomic scatter-adds whose order varies with
    the thread schedule (measured: 3e-8 between two renders of one path_rr image, 2.4e-6
    between volpath_raymarch and path_rr on the Cornell box at 16x16, 8 spp)."""
    rel = np.abs(a - b) / np.maximum(np.abs(b), 1e-3)
    assert rel.max() < rtol, f"max relative difference {rel.max():.3g}"


def assert_same_expectation(a: stats.Estimate, b: stats.Estimate, name: str, **kw):
    """docs/validation.md's three checks; on failure the images and the z map are written."""
    result = stats.compare(a, b, **kw)
    if not result.passed:
        FAILURES.mkdir(parents=True, exist_ok=True)
        for tag, img in (("candidate", a.mean), ("reference", b.mean), ("z", result.z)):
            mi.Bitmap(np.ascontiguousarray(img, dtype=np.float32)).write(str(FAILURES / f"{name}_{tag}.exr"))
    assert result.passed, f"{name}: {result.summary()} (images in {FAILURES})"
    return result


def assert_mean_equals(images, expected: float, name: str, alpha: float = 1e-3):
    """t-test of independent pixel values (one channel: gray scenes) against ``expected``."""
    res = stats.t_test(np.asarray(images)[..., 0], expected)
    assert res.p > alpha, f"{name}: {res.summary()}"
    return res


# -- media scenes and segments shared by the volumetric integrators' tests ----------------
#: the wavelengths (nm) at which :func:`medium_at` evaluates in spectral variants
PROBE_NM = (450.0, 520.0, 600.0, 680.0)
#: Mitsuba's luminance weights (mono variants render an RGB value's luminance)
LUMINANCE = np.array([0.212671, 0.715160, 0.072169])


def medium_at(medium, method: str, points) -> np.ndarray:
    """``medium.<method>(mei)`` (e.g. ``eval_sigma_t``, ``get_radiance``) at world
    ``points`` (N x 3), as a (channels, N) array (spectral variants: at ``PROBE_NM``)."""
    points = np.asarray(points, dtype=np.float32)
    mei = dr.zeros(mi.MediumInteraction3f, len(points))
    mei.p = mi.Point3f(*(mi.Float(points[:, i]) for i in range(3)))
    if mi.is_spectral:
        mei.wavelengths = mi.Spectrum(*PROBE_NM)
    return np.array(getattr(medium, method)(mei))


def emitted_in_variant(rgb) -> np.ndarray:
    """An RGB radiance as the active variant renders it at :func:`medium_at`'s
    wavelengths, (channels,): itself, its luminance in mono, d65 times the upsampled
    colour in spectral variants (an emitter's rule, Mitsuba's own ``d65`` plugin)."""
    rgb = np.asarray(rgb, np.float64)
    if mi.is_rgb:
        return rgb
    if mi.is_monochromatic:
        return np.array([LUMINANCE @ rgb])
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.wavelengths = mi.Spectrum(*PROBE_NM)
    return np.array(mi.load_dict({"type": "d65", "color": rgb.tolist()}).eval(si)).ravel()


def segment(n):
    """``n`` copies of a fixed ray and the length of the segment tested along it."""
    o = mi.Point3f(-0.2, 0.13, 0.31)
    d = dr.normalize(mi.Vector3f(1.0, 0.7, 0.4))
    return mi.Ray3f(dr.zeros(mi.Point3f, n) + o, dr.zeros(mi.Vector3f, n) + d), 1.6


def exact_optical_depth(medium, steps=40000, ray_segment=None):
    """Midpoint rule with ``steps`` points over ``ray_segment(1)`` (default
    :func:`segment`; error ~1e-7 for its smooth trilinear field)."""
    ray, length = (ray_segment or segment)(1)
    t = (dr.arange(mi.Float, steps) + 0.5) * (length / steps)
    mei = dr.zeros(mi.MediumInteraction3f, steps)
    mei.p = ray.o + ray.d * t
    sigma = np.array(medium.eval_sigma_t(mei))
    # the medium exists inside its bounding box only (as for Mitsuba's media)
    p = np.array(mei.p)
    inside = np.all((p >= np.array(medium.bbox.min)[:, None]) &
                    (p <= np.array(medium.bbox.max)[:, None]), axis=0)
    return (sigma * inside).sum(axis=1) * length / steps


def hard_grid(tmp_path, kind):
    """An 8^3 grid: all zero (``empty``) or one voxel of 1e4 (``one_voxel``)."""
    data = np.zeros((8, 8, 8), np.float32)
    if kind == "one_voxel":
        data[4, 3, 5] = 1e4
    path = tmp_path / f"{kind}.npy"
    np.save(path, data)
    return grid(filename=str(path), scale=1.0)


#: media for the hard-case tests, by name: a function of a temporary folder
HARD_MEDIA = {
    "homogeneous_1e-4": lambda tmp: homogeneous(1e-4),
    "homogeneous_1e4": lambda tmp: homogeneous(1e4),
    "homogeneous_chromatic_extreme": lambda tmp: homogeneous([1e-4, 1.0, 1e4]),
    "grid_1e-4": lambda tmp: grid(scale=1e-4),
    "grid_1e4": lambda tmp: grid(scale=1e4),
    "grid_chromatic_1e4": lambda tmp: grid(scale=1e4, sigma_t=[1.0, 1e-4, 0.0]),
    "empty_grid": lambda tmp: hard_grid(tmp, "empty"),
    "one_dense_voxel": lambda tmp: hard_grid(tmp, "one_voxel"),
}


def emissive_slab(Le: float, **medium) -> mi.Scene:
    """A purely absorbing emissive ``grid_medium`` (``medium`` parameters) in the cube
    [-1, 1]^3, seen head-on through its 2 units by an 8x8 orthographic sensor."""
    return mi.load_dict({
        "type": "scene",
        "slab": {"type": "cube", "bsdf": {"type": "null"},
                 "interior": {"type": "grid_medium", "albedo": 0.0, "emission": Le, **medium}},
        "sensor": {"type": "orthographic",
                   "to_world": mi.ScalarTransform4f().look_at([0, 0, 5], [0, 0, 0], [0, 1, 0])
                   @ mi.ScalarTransform4f().scale([0.5, 0.5, 1]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 16}}})


# -- majorant bounds, property-tested over random rays ------------------------------------
N_RAYS = 4096


def grid_segments(grid, ray: mi.Ray3f, t_start, t_stop, max_segments: int | None = None):
    """All segments of a :class:`~mitsuba_plugins.tracking.majorant_grid.MajorantGrid` along ``ray`` as numpy
    arrays ``(t0, t1, sigma_maj, valid)`` of shape ``(n_rays, n_segments)``."""
    rx, ry, rz = grid.resolution
    limit = max_segments or (rx + ry + rz + 3)
    state = grid.start(ray, mi.Float(t_start), mi.Float(t_stop))
    n = dr.width(ray)
    out = []
    for _ in range(limit):
        active = state.t < state.t_end
        t0, t1, sigma_maj, _, state = grid.next_bounds(state, active, minorant=False)
        dr.eval(t0, t1, sigma_maj, active, state.t, state.cell)
        out.append(tuple(np.broadcast_to(np.asarray(x), (n,))
                         for x in (t0, t1, sigma_maj, active)))
    return tuple(np.stack(x, axis=1) for x in zip(*out))


def build_majorants(data: np.ndarray, resolution, weights=1.0) -> np.ndarray:
    """Cell bounds ``(Rz, Ry, Rx)`` of a whole ``(Z, Y, X, C)`` array."""
    from mitsuba_plugins.grids.bounds import MajorantBuilder
    return MajorantBuilder(data.shape, resolution, weights).add_all(data).finish()


def random_rays(rng, n, spread=2.5):
    """Origins in and around the box, directions with some exactly axis-parallel
    components (the DDA's divide-by-zero case)."""
    o = rng.uniform(-spread, spread, (n, 3))
    d = rng.normal(size=(n, 3))
    d[rng.random((n, 3)) < 0.1] = 0.0
    d[np.all(d == 0, axis=1)] = (0.0, 0.0, 1.0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return mi.Ray3f(mi.Point3f(*(mi.Float(o[:, i].astype(np.float32)) for i in range(3))),
                    mi.Vector3f(*(mi.Float(d[:, i].astype(np.float32)) for i in range(3)))), o, d


def check_segment_bounds(medium, grid):
    """Along every segment of random rays, sigma_t at random points (all channels; in a
    spectral variant at random wavelengths over the visible range) <= sigma_maj; returns
    the segments' majorants."""
    rng = np.random.default_rng(3)
    ray, _, _ = random_rays(rng, N_RAYS, spread=3.0)
    t0, t1, sigma_maj, valid = grid_segments(grid, ray, 0.0, 8.0)
    k = 8  # points per segment
    rows, cols = np.nonzero(valid)
    u = rng.random((rows.size, k))
    t = t0[rows, cols, None] + u * (t1 - t0)[rows, cols, None]
    o = np.array([ray.o.x, ray.o.y, ray.o.z]).T[rows]
    d = np.array([ray.d.x, ray.d.y, ray.d.z]).T[rows]
    p = (o[:, None, :] + t[..., None] * d[:, None, :]).reshape(-1, 3).astype(np.float32)
    mei = dr.zeros(mi.MediumInteraction3f, p.shape[0])
    mei.p = mi.Point3f(*(mi.Float(p[:, i]) for i in range(3)))
    if mi.is_spectral:
        mei.wavelengths = mi.Spectrum(*[mi.Float(rng.uniform(
            mi.MI_CIE_MIN, mi.MI_CIE_MAX, p.shape[0]).astype(np.float32)) for _ in range(4)])
    channels = dr.size_v(mi.Spectrum)
    if hasattr(medium, "eval_sigma_t"):
        sigma_t = medium.eval_sigma_t(mei)
    else:                                    # a Mitsuba medium
        _, _, sigma_t = medium.get_scattering_coefficients(mei)
    sigma_t = np.array(sigma_t).reshape(channels, -1).T.max(axis=1)
    bound = np.repeat(sigma_maj[rows, cols], k)
    worst = np.max(sigma_t - bound)
    assert worst <= 0.0, f"sigma_t exceeds the segment majorant by {worst}"
    return sigma_maj[valid]


# -- OpenVDB files written by OpenVDB itself ----------------------------------------------
def software_dense_textures(monkeypatch) -> None:
    """Dense storage interpolates in software for the rest of the test, as sparse bricks
    do (CUDA's hardware interpolation has 8-bit weights: lookups then differ by up to
    2^-9 of the maximum; elsewhere nothing changes), for tests that compare the two
    storages' bookkeeping lookup for lookup."""
    from mitsuba_plugins.grids import stores
    texture = stores.mi.Texture3f
    monkeypatch.setattr(stores.mi, "Texture3f",
                        lambda *a, **kw: texture(*a, **{**kw, "use_accel": False}))


def make_vdb(path, *bodies: str, **arrays) -> dict:
    """Run ``bodies`` (code pieces, each dedented) in Debian's Python with ``vdb`` (pyopenvdb) and ``np`` imported, the
    ``arrays`` loaded by name; it appends grids to ``grids`` and may fill the dict ``out``
    (returned, e.g. world positions from the file's transform). Writes ``path``."""
    files = {}
    for name, array in arrays.items():
        files[name] = str(path.with_name(f"{name}.npy"))
        np.save(files[name], array)
    script = "import json, pyopenvdb as vdb, numpy as np\ngrids, out = [], {}\n"
    script += "".join(f"{k} = np.load({v!r})\n" for k, v in files.items())
    script += "".join(textwrap.dedent(b).strip("\n") + "\n" for b in bodies)
    script += f"\nvdb.write({str(path)!r}, grids=grids)\nprint(json.dumps(out))\n"
    proc = subprocess.run([vdb_openvdb.DEFAULT_PYTHON, "-c", script], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def spectra_of(values):
    """``values`` as the active variant's spectra, ``[(channel values, spectrum)]``: one
    spectrum of as many channels (repeated to 4 wavelengths in spectral variants), or
    one per value in mono."""
    n = dr.size_v(mi.Spectrum)
    groups = [[v] for v in values] if n < len(values) else [np.resize(values, n)]
    return [(list(g), mi.Spectrum(*map(float, g))) for g in groups]


def assert_slab_matches(scene, img: np.ndarray, reference: str, what: str) -> None:
    """``img`` of the emissive slab ``scene`` against ``reference``'s render of it (256 spp,
    another seed): Welch test per pixel sample, per channel, alpha 1e-3. For a spectral
    variant's chromatic slab, whose per-channel closed form does not hold."""
    from mitsuba_plugins.tools import gradcheck
    ref = np.array(mi.render(scene, integrator=mi.load_dict({"type": reference}), seed=4,
                             spp=256))
    for c in range(img.shape[-1]):
        t, p = gradcheck.welch(img[..., c].ravel(), ref[..., c].ravel())
        assert p > 1e-3, f"{what} channel {c}: {img[..., c].mean():.4f} against " \
                         f"{reference} {ref[..., c].mean():.4f}, t = {t:.2f}"

