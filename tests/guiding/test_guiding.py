"""Path guiding (``volpath_delta``'s and ``path_rr``'s ``guiding``, docs/method.md section
13): the field's
pdf is the density of its own samples (chi-square over equal-area bins), guided renders
estimate the same image as unguided ones (docs/validation.md's Welch z-tests, disjoint
seeds) and the furnace's analytic 1 (t-test), in every variant the suite runs; training
learns where the light is; bad parameters are refused (gradient renders:
tests/integrators/test_gradients.py)."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy import stats as scipy_stats

from helpers import (assert_mean_equals, assert_same_expectation, cached_estimate, camera, grid,
                     homogeneous, load, loaded, media_scene, render)
from mitsuba_plugins import guided_render
from mitsuba_plugins.guiding import distance, sampling
from mitsuba_plugins.guiding.distance import LightGrid, Segment
from mitsuba_plugins.guiding.field import (ACC_STRIDE, MIN_RECORDS, NEE_MIN, NEE_SHARE,
                                           NEE_SIDES, PORTAL_PLANES, PORTAL_POOL,
                                           GuidingField,
                                           HistogramField, media_bounds)
from mitsuba_plugins.tracking import equiangular

GUIDED = {"type": "volpath_delta", "guiding": "volumes"}


@pytest.fixture(autouse=True, scope="module")
def _fresh_kernels_after():
    """Drop this module's compiled kernels when it ends. Dr.Jit 1.5's LLVM backend can
    abort a later kernel of the same process with "invalid redefinition of function"
    depending on what the process compiled before (docs/validation.md): the guided
    renders' kernels did that to a gradient test of the spectral and mono suites."""
    yield
    dr.flush_kernel_cache()


#: the rule's own value (the fixture below lowers it for every other test)
DEFAULT_MIN_TRAINING_PATHS = guided_render.MIN_TRAINING_PATHS
DEFAULT_CPU_MIN_PASS_PATHS = guided_render.MIN_PASS_PATHS["llvm"]


@pytest.fixture(autouse=True)
def _guide_small_images(monkeypatch):
    """This module's images are small (32x32 and less): guide them anyway
    (``guided_render.MIN_TRAINING_PATHS`` would render them in one plain pass), with the
    CPU's training passes unmerged (``MIN_PASS_PATHS``, whose floor would leave a 64-spp
    render of 32x32 one training pass); their own tests set them back."""
    monkeypatch.setattr(guided_render, "MIN_TRAINING_PATHS", 0)
    monkeypatch.setitem(guided_render.MIN_PASS_PATHS, "llvm", 0)


def _accumulate(field, sums, records):
    """As if a pass had recorded ``sums`` (5 x cells: W, Vx, Vy, Vz, N) and ``records``
    vertices per cell into ``field``'s accumulators (``field.ACC_STRIDE`` per cell)."""
    acc = np.zeros((field.cells, ACC_STRIDE), np.float32)
    acc[:, :5], acc[:, 5] = np.asarray(sums).T, records
    field.acc = mi.Float(acc.ravel())


def _field_with_lobe(mu, r, records=1000):
    """A 2^3 field whose cell 0 has the lobe of mean cosine ``r`` around ``mu``."""
    field = GuidingField(mi.ScalarBoundingBox3f([0, 0, 0], [1, 1, 1]), resolution=2)
    sums = np.zeros((5, field.cells))
    sums[0, 0] = 1.0
    sums[1:4, 0] = r * np.asarray(mu) / np.linalg.norm(mu)
    sums[4, 0] = records
    _accumulate(field, sums, records)
    assert field.update() == (1 if r > 0 else 0)
    return field


def _fitted(directions: np.ndarray, values: np.ndarray, noise_aware: bool) -> GuidingField:
    """A one-cell field fitted (plainly or noise-aware) to one pass of records."""
    field = GuidingField(mi.ScalarBoundingBox3f([0, 0, 0], [1, 1, 1]), resolution=1)
    field.NOISE_AWARE = noise_aware
    d = mi.Vector3f(*(mi.Float(c.astype(np.float32)) for c in directions.T))
    field.record(mi.UInt32(np.zeros(len(values), np.uint32)), d,
                 mi.Float(values.astype(np.float32)), mi.Bool(True))
    field.update()
    return field


def test_lobes_are_fitted_to_what_the_records_resolve():
    """The lobe's mean cosine is ``sqrt(max(|V|^2 - S2, 0)) / W`` (``GuidingField.update``),
    not ``|V| / W``. Isotropic light recorded with heavy-tailed values (lognormal, sigma
    1.5, as records in a dense medium of albedo near 1), 400 records, 10 seeds: the plain
    fit finds a lobe in its noise every time (mean cosines 0.04-0.22); the noise-aware fit
    is flatter in every seed, uniform (kappa 0) in at least 4 of 10 (6 measured: |V|^2 -
    S2 is centred on 0 there, so it is positive in about 40% of draws) and its mean kappa
    at most 0.4 of the plain one's (0.2 measured). Light from one side (4000 directions
    from a lobe of mean cosine 0.6, the same values): both fits keep the lobe, within 10
    degrees of its axis, with kappas within 15% of each other."""
    rng = np.random.default_rng(17)
    kappas = []
    for _ in range(10):
        d = rng.normal(size=(400, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        values = rng.lognormal(0.0, 1.5, 400)
        kappas.append([float(np.array(_fitted(d, values, aware).kappa)[0])
                       for aware in (True, False)])
    aware, plain = np.array(kappas).T
    assert np.all(plain > 0), plain
    assert np.all(aware < plain), (aware, plain)
    assert np.sum(aware == 0) >= 4, aware
    assert aware.mean() <= 0.4 * plain.mean(), (aware, plain)
    source = _field_with_lobe([0.0, 0.0, 1.0], 0.6)
    u = mi.Point2f(*(mi.Float(rng.random(4000).astype(np.float32)) for _ in range(2)))
    d = np.array(source.sample(mi.UInt32(0), u)).reshape(3, -1).T
    values = rng.lognormal(0.0, 1.5, len(d))
    lobes = []
    for aware_fit in (True, False):
        mu, kappa = (np.array(x) for x in _fitted(d, values, aware_fit).lobe(mi.UInt32(0)))
        assert float(mu.reshape(3)[2]) > math.cos(math.radians(10)), mu
        lobes.append(float(kappa[0]))
    assert lobes[1] > 0 and lobes[0] == pytest.approx(lobes[1], rel=0.15), lobes


@pytest.mark.parametrize("r", [0.0, 0.5, 0.85])
def test_field_pdf_is_the_density_of_its_samples(r):
    """Chi-square test (alpha 1e-3) of 2^20 samples over 8 x 16 equal-area bins against the
    pdf integrated over each bin (16 x 16 midpoints per bin); the pdf integrates to 1."""
    _assert_density_of_samples(_field_with_lobe([0.3, -0.5, 0.8], r))


@pytest.mark.parametrize("bins", [1, 5, 16])
def test_histogram_pdf_is_the_density_of_its_samples(bins):
    """The same test for a directional histogram (``path_rr``'s ``guiding_bins``) of
    random bin weights, a fifth of them 0 (the uniform share keeps every bin's density
    above 0); the test's 8 x 16 bins do not line up with the histogram's."""
    field = HistogramField(mi.ScalarBoundingBox3f([0, 0, 0], [1, 1, 1]), resolution=2,
                           bins=bins)
    rng = np.random.default_rng(bins)
    weights = rng.gamma(0.5, size=(field.cells, field.size)) * \
        (rng.random((field.cells, field.size)) > 0.2)
    field.acc_hist = mi.Float(weights.ravel().astype(np.float32))
    _accumulate(field, np.array([1, 0.3, 0, 0, 100])[:, None].repeat(field.cells, 1), 100)
    assert field.update() == field.cells
    _assert_density_of_samples(field, cell=3, mass=_histogram_mass)


def _rectangle_solid_angle(x, centre, half) -> float:
    """The solid angle of an axis-aligned rectangle (one half-extent 0) seen from ``x``:
    two triangles by Van Oosterom and Strackee's formula."""
    axes = [k for k in range(3) if half[k] > 0]
    corners = []
    for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        c = np.array(centre, np.float64)
        c[axes[0]] += su * half[axes[0]]
        c[axes[1]] += sv * half[axes[1]]
        corners.append(c - np.array(x, np.float64))

    def triangle(a, b, c):
        la, lb, lc = (np.linalg.norm(v) for v in (a, b, c))
        num = abs(np.dot(a, np.cross(b, c)))
        den = la * lb * lc + np.dot(a, b) * lc + np.dot(a, c) * lb + np.dot(b, c) * la
        return 2.0 * np.arctan2(num, den)
    return triangle(corners[0], corners[1], corners[2]) + \
        triangle(corners[0], corners[2], corners[3])


@pytest.mark.parametrize("normal", [0, 1, 2])
def test_portal_pdf_is_the_density_of_its_samples(normal):
    """Directions toward points uniform on a portal (``HistogramField.portal_sample``)
    against its density (``portal_pdf``): ``E[1 / pdf]`` over 2^20 samples is the
    rectangle's solid angle (exact: Van Oosterom-Strackee) within 4 standard errors of
    the mean, which holds only if ``pdf`` is the samples' density on their support; and
    the pdf integrates to 1 over the sphere (a 1024 x 2048 midpoint grid, 1%: the
    rectangle's edges cut cells)."""
    half = [0.5, 0.3, 0.7]
    half[normal] = 0.0
    centre, x = [0.4, -0.2, 0.6], [-0.1, 0.3, -0.3]
    inv_area = 1.0 / (4.0 * np.prod([h for h in half if h > 0]))
    c, h = mi.Point3f(*centre), mi.Vector3f(*half)
    rng = np.random.default_rng(normal)
    n = 1 << 20
    u = mi.Point2f(*(mi.Float(rng.random(n).astype(np.float32)) for _ in range(2)))
    y = HistogramField.portal_sample(c, h, u)
    d = dr.normalize(y - mi.Point3f(*x))
    p = np.array(HistogramField.portal_pdf(c, h, mi.Float(inv_area), mi.Point3f(*x), d),
                 np.float64)
    assert (p > 0).all()
    omega = _rectangle_solid_angle(x, centre, half)
    se = np.std(1.0 / p) / np.sqrt(n)
    assert abs(np.mean(1.0 / p) - omega) < 4 * se + 1e-6, (np.mean(1.0 / p), omega, se)
    Z, _, dirs = _sphere_midpoints(1024, 2048)
    dens = np.array(HistogramField.portal_pdf(c, h, mi.Float(inv_area), mi.Point3f(*x), dirs))
    assert dens.sum() * 4 * np.pi / Z.size == pytest.approx(1.0, rel=0.01)


def _door_records(field, rng, n: int = 4000) -> tuple:
    """Records of one cell whose light all came through a door (a 0.2 x 0.4 rectangle in
    the plane z = 0.8; rays from points uniform in the cell toward points uniform on it,
    their next vertex beyond it), as ``HistogramField.portal_source``; and the cell."""
    origin = rng.uniform([0.27, 0.27, 0.02], [0.48, 0.48, 0.23], (n, 3))
    target = np.column_stack([rng.uniform(0.4, 0.6, n), rng.uniform(0.2, 0.6, n),
                              np.full(n, 0.8)])
    d = target - origin
    length = np.linalg.norm(d, axis=1)
    cell = np.array(field.cell(mi.Point3f(*origin.T.astype(np.float32))))
    assert (cell == cell[0]).all()
    return np.column_stack([cell, origin, d / length[:, None], length + 0.1,
                            rng.uniform(0.5, 1.5, n)]), int(cell[0])


def _pool(field, cell: int) -> np.ndarray:
    """The cells that find one portal with ``cell`` (``PORTAL_POOL`` per axis)."""
    r, q = field.resolution, PORTAL_POOL
    i = np.arange(field.cells)
    same = lambda c: ((i % r) // q == (c % r) // q) & ((i // r) % r // q == (c // r) % r // q) \
        & ((i // (r * r)) // q == (c // (r * r)) // q)
    return same(cell)


@pytest.mark.parametrize("wall", [False, True])
def test_portals_find_a_door(wall):
    """From :func:`_door_records`, ``HistogramField.portals`` puts the cell's portal in a
    plane of normal z, centred on the door within 0.05 and as wide: within two candidate
    planes' spacings of 0.8 among planes across the box (at least 90% of the door's
    width per axis), or, given the wall's plane z = 0.8 among the scene's own planes
    (``geometry_planes``), in it and within 2% narrower and 10% wider than the door. The cells of the same pool share it; the
    others have none."""
    field = HistogramField(mi.ScalarBoundingBox3f([0, 0, 0], [1, 1, 1]), resolution=4)
    if wall:
        field.geometry_planes = [np.array([0.0, 1.0]), np.array([0.0, 1.0]),
                                 np.array([0.0, 0.8, 1.0])]
    field.portal_source, cell = _door_records(field, np.random.default_rng(3))
    table = field.portals()
    centre, half = table[cell, :3], table[cell, 3:]
    assert half[2] == 0 and half[0] > 0 and half[1] > 0
    assert abs(centre[2] - 0.8) <= (1e-9 if wall else 2.0 / PORTAL_PLANES)
    assert np.allclose(centre[:2], [0.5, 0.4], atol=0.05), centre
    low = 0.98 if wall else 0.9       # (a plane before the door sees it a little smaller)
    assert half[0] >= 0.1 * low and half[1] >= 0.2 * low, half
    if wall:
        assert half[0] <= 0.11 and half[1] <= 0.22, half
    pool = _pool(field, cell)
    assert pool.sum() == 8 and (table[pool] == table[cell]).all()
    assert (table[~pool] == 0).all()


def test_rectangle_solid_angle():
    """``rectangle_solid_angle`` against Van Oosterom and Strackee's two triangles for
    rectangles on and off the point's foot, near and far; a half-plane's limit 2 pi
    over the whole plane, and 0 in the plane itself."""
    from mitsuba_plugins.guiding.field import rectangle_solid_angle
    rng = np.random.default_rng(5)
    for _ in range(20):
        u0, v0 = rng.uniform(-1.0, 1.0, 2)
        u1, v1 = u0 + rng.uniform(0.01, 2.0), v0 + rng.uniform(0.01, 2.0)
        h = rng.uniform(0.05, 3.0)
        exact = _rectangle_solid_angle([0.0, 0.0, 0.0], [(u0 + u1) / 2, (v0 + v1) / 2, h],
                                       [(u1 - u0) / 2, (v1 - v0) / 2, 0.0])
        assert rectangle_solid_angle(u0, u1, v0, v1, h) == pytest.approx(exact, rel=1e-9)
    assert rectangle_solid_angle(-1e6, 1e6, -1e6, 1e6, 1.0) == pytest.approx(2 * np.pi, 1e-5)
    assert rectangle_solid_angle(-1.0, 1.0, -1.0, 1.0, 0.0) == 0.0


def test_geometry_planes_are_the_walls():
    """``geometry_planes`` of the guiding benchmark's door room (rectangles Mitsuba merges
    into meshes): per axis the coordinates of its walls, floors and ceilings (and the
    light's plane y = -0.99), each once; none of a sphere."""
    from benchmarks.guiding import door_room
    from mitsuba_plugins.guiding.field import geometry_planes
    planes = geometry_planes(door_room(8))
    assert np.allclose(planes[0], [-1.0, 1.0])
    assert np.allclose(planes[1], [-1.0, -0.99, 1.0])
    assert np.allclose(planes[2], [-1.0, 1.0, 2.6])
    ball = mi.load_dict({"type": "scene", "ball": {"type": "sphere"}})
    assert all(len(p) == 0 for p in geometry_planes(ball))


def test_guided_surfaces_with_portals_estimate_the_same_image():
    """``path_rr`` guided with portals (the default ``guiding_portal``) against plain
    ``path_rr`` in the guiding benchmark's door room (a room lit only through a door;
    32x32, 16 passes of 128 spp each, disjoint seeds): docs/validation.md's three checks.
    A render of the same settings must have found portals, or the test would not test
    them."""
    from benchmarks.guiding import door_room
    integrator = {"type": "path_rr", "max_depth": 8, "guiding": "surfaces"}
    probe = mi.load_dict(integrator)
    mi.render(door_room(32), integrator=probe, spp=128, seed=1)
    assert probe.guiding_report.field.has_portals
    a = cached_estimate("door_room:32", lambda: door_room(32), integrator, passes=16,
                        spp=128, seed=3000)
    b = cached_estimate("door_room:32", lambda: door_room(32),
                        {"type": "path_rr", "max_depth": 8}, passes=16, spp=128)
    assert_same_expectation(a, b, "guiding-portals-door_room")


@pytest.mark.parametrize("bins", [5, 16])
def test_guide_table_finds_the_bin_a_binary_search_finds(bins):
    """For every u at and beside (one float32 step each way) each bin's cumulative
    probability and each of the table's interval bounds, and 2^16 uniform ones, the
    guide table gives the first bin whose cumulative probability (float32, as the device
    holds it) reaches u: in trained cells and in a uniform one (bin count 5: its bounds
    j / 25 are not float32s)."""
    field = HistogramField(mi.ScalarBoundingBox3f([0, 0, 0], [1, 1, 1]), resolution=2,
                           bins=bins)
    rng = np.random.default_rng(bins + 1)
    weights = rng.gamma(0.5, size=(field.cells, field.size)) * \
        (rng.random((field.cells, field.size)) > 0.2)
    field.acc_hist = mi.Float(weights.ravel().astype(np.float32))
    _accumulate(field, np.array([1, 0.3, 0, 0, 100])[:, None].repeat(field.cells, 1), 100)
    field.update()
    untrained = HistogramField(mi.ScalarBoundingBox3f([0, 0, 0], [1, 1, 1]), resolution=2,
                               bins=bins)          # uniform: its sums lie on the grid
    for field, cell in ((field, 0), (field, 5), (untrained, 0)):
        row = np.array(field.cdf, np.float32).reshape(field.cells, field.size)[cell]
        grid = (np.arange(field.size) / field.size).astype(np.float32)
        u = np.concatenate([row, np.nextafter(row, 0), np.nextafter(row, 1),
                            rng.random(1 << 16).astype(np.float32),
                            grid, np.nextafter(grid, 0), np.nextafter(grid, 1)])
        u = u[(u >= 0) & (u < 1)].astype(np.float32)
        found = np.array(field.find_bin(mi.UInt32(np.full(u.size, cell, np.uint32)),
                                        mi.Float(u)))
        expected = np.minimum(np.searchsorted(row, u, side="left"), field.size - 1)
        assert np.array_equal(found, expected)


def _sphere_midpoints(nz: int, nphi: int):
    """``(Z, P, dirs)``: the midpoints of an ``nz x nphi`` grid of equal-area (z, phi)
    bins over the sphere, as arrays and as Dr.Jit directions (z-major)."""
    z = -1 + 2 * (np.arange(nz) + 0.5) / nz
    phi = 2 * np.pi * (np.arange(nphi) + 0.5) / nphi
    Z, P = np.meshgrid(z, phi, indexing="ij")
    s = np.sqrt(1 - Z * Z)
    dirs = mi.Vector3f(*(mi.Float(v.ravel().astype(np.float32)) for v in
                         (s * np.cos(P), s * np.sin(P), Z)))
    return Z, P, dirs


def _histogram_mass(field, cell, nz, nphi):
    """The exact probability of each of the test's ``nz x nphi`` (z, phi) bins under a
    histogram field's pdf, evaluated at its bins' centres: the density is constant on
    each of its bins, and solid angle is area in (z, phi)."""
    n = field.bins
    Z, _, dirs = _sphere_midpoints(n, n)
    density = np.array(field.pdf(mi.UInt32(np.full(Z.size, cell, np.uint32)), dirs)).reshape(n, n)

    def overlap(edges_a, edges_b):
        lo = np.maximum(edges_a[:-1, None], edges_b[None, :-1])
        hi = np.minimum(edges_a[1:, None], edges_b[None, 1:])
        return np.clip(hi - lo, 0, None)          # (test bins, histogram bins)
    oz = overlap(np.linspace(-1, 1, nz + 1), np.linspace(-1, 1, n + 1))
    op = overlap(np.linspace(0, 2 * np.pi, nphi + 1), np.linspace(0, 2 * np.pi, n + 1))
    return (oz @ density @ op.T).ravel()


def _quadrature_mass(field, cell, nz, nphi):
    """The pdf integrated over each test bin by 16 x 16 midpoints (smooth pdfs)."""
    m = 16
    Z, _, dirs = _sphere_midpoints(nz * m, nphi * m)
    pdf = np.array(field.pdf(mi.UInt32(np.full(Z.size, cell, np.uint32)), dirs)).reshape(Z.shape)
    return (pdf * 4 * np.pi / Z.size).reshape(nz, m, nphi, m).sum(axis=(1, 3)).ravel()


def _assert_density_of_samples(field, cell=0, mass=_quadrature_mass):
    n = 1 << 20
    rng = np.random.default_rng(7)
    u = mi.Point2f(*(mi.Float(rng.random(n).astype(np.float32)) for _ in range(2)))
    d = np.array(field.sample(mi.UInt32(cell), u)).reshape(3, -1)
    assert np.allclose(np.linalg.norm(d, axis=0), 1.0, atol=1e-5)
    nz, nphi = 8, 16
    phi = np.mod(np.arctan2(d[1], d[0]), 2 * np.pi)
    bins = np.minimum(((d[2] + 1) / 2 * nz).astype(int), nz - 1) * nphi + \
        np.minimum((phi / (2 * np.pi) * nphi).astype(int), nphi - 1)
    observed = np.bincount(bins, minlength=nz * nphi)
    mass = mass(field, cell, nz, nphi)
    assert mass.sum() == pytest.approx(1.0, abs=2e-3)
    expected = mass / mass.sum() * n
    chi2 = float(((observed - expected) ** 2 / expected).sum())
    assert scipy_stats.chi2.sf(chi2, nz * nphi - 1) > 1e-3, chi2


def _dense_ball():
    return media_scene(homogeneous(8.0, albedo=0.95, g=0.5), env=0)


def _chromatic_ball():
    return media_scene(homogeneous([2.0, 5.0, 9.0], albedo=0.9, g=0.3))


def _smoke():
    return media_scene(grid(scale=20.0, albedo=0.9))


def _camera_inside():
    fog = homogeneous(0.6, albedo=0.9, g=0.6)
    return media_scene(extra={"fog": {"type": "sphere", "radius": 6.0, "bsdf": {"type": "null"},
                                      "interior": fog}},
                       sensor=camera(medium=fog), env=0.4)


def _lit_fog():
    """A thin fog ball with a point light inside it and a small area light outside: the
    guided point's emitter samples of delta and area lights, segments that end at the
    ball's null boundary (every lane samples at the point) and at the floor (collided
    lanes only)."""
    return media_scene(homogeneous(1.5, albedo=0.9, g=0.3), env=0, extra={
        "point": {"type": "point", "position": [0.3, 0.2, 0.1],
                  "intensity": {"type": "rgb", "value": 2.0}}})


def _thin_fog():
    """A thin fog ball under the small light with a diffuse core, nothing behind it:
    segments that pass through the ball gather light at their guided point although the
    path then sees nothing (a 3% bias once: those pixels were dropped as empty), and
    segments that end at the core sample at the point only where the flight collided
    (weighted by the collision probability)."""
    scene = media_scene(None, env=0, as_dict=True)
    scene["fog"] = homogeneous(1.5, albedo=0.9, g=0.3)
    scene["ball"] = {"type": "sphere", "bsdf": {"type": "null"},
                     "interior": {"type": "ref", "id": "fog"}}
    scene["core"] = {"type": "sphere", "radius": 0.4, "exterior": {"type": "ref", "id": "fog"},
                     "bsdf": {"type": "diffuse"}}
    return mi.load_dict(scene)


def _microflake_fog():
    """A fog ball whose phase function (SGGX) is not symmetric about the incident
    direction: resampling draws its candidates from it, not by turning the first."""
    fog = homogeneous(2.0, albedo=0.9)
    S = np.array([1.0, 0.2, 0.5, 0.1, 0.0, 0.0], np.float32).reshape(1, 1, 1, 6)
    fog["phase"] = {"type": "sggx", "S": {"type": "gridvolume", "grid": mi.VolumeGrid(S)}}
    return media_scene(fog, env=0)


def _lamp_under_sky():
    """A lamp at the centre of a forward-scattering fog ball under an environment: its
    light at guided points is next-event estimation's alone (``LightGrid.on_lamp``),
    the environment's keeps both techniques, and rays that escape to it never count as
    hitting the lamp whose bounds hold the origin."""
    d = media_scene(homogeneous(1.0, albedo=0.9, g=0.7), env=0.5, as_dict=True)
    d["lamp"] = {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 0.06,
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 100.0}}}
    return mi.load_dict(d)


def _cube_pair(dense: float = 300.0):
    """A dense cube (optical depth ``dense`` across one side) beside a thin one, under the
    small light: cells of the light grid straddle both, and the dense cube's segments take
    no guided points (``LightGrid.takes``) while the thin one's do."""
    null = {"type": "null"}
    return media_scene(env=0, extra={
        "dense": {"type": "cube", "bsdf": null, "interior": homogeneous(dense, albedo=0.9),
                  "to_world": mi.ScalarTransform4f().translate([-0.55, 0, 0]).scale(0.5)},
        "thin": {"type": "cube", "bsdf": null, "interior": homogeneous(1.0, albedo=0.9),
                 "to_world": mi.ScalarTransform4f().translate([0.55, 0, 0]).scale(0.5)}})


CASES = {"dense_ball": _dense_ball, "chromatic_ball": _chromatic_ball, "smoke": _smoke,
         "camera_inside": _camera_inside, "lit_fog": _lit_fog, "thin_fog": _thin_fog,
         "microflake_fog": _microflake_fog, "lamp_under_sky": _lamp_under_sky,
         "cube_pair": _cube_pair}


def _vectors(a: np.ndarray) -> mi.Vector3f:
    """A (3, n) array as ``n`` Dr.Jit vectors."""
    return mi.Vector3f(*(mi.Float(v.astype(np.float32)) for v in a))


def test_turned_candidates_keep_the_angle_to_the_axis():
    """Resampling's candidates turned about the incident direction: unit vectors at the
    first one's angle to the axis, evenly around it (their sum is along the axis)."""
    rng = np.random.default_rng(3)
    axis, d = (rng.normal(size=(3, 64)) for _ in range(2))
    axis, d = axis / np.linalg.norm(axis, axis=0), d / np.linalg.norm(d, axis=0)
    A, D = _vectors(axis), _vectors(d)
    out = [np.array(v).reshape(3, -1) for v in sampling.turned(A, D, 4)]
    for v in out:
        assert np.allclose(np.linalg.norm(v, axis=0), 1.0, atol=1e-5)
        assert np.allclose((v * axis).sum(0), (d * axis).sum(0), atol=1e-5)
    assert np.allclose(d + sum(out), 4 * (d * axis).sum(0) * axis, atol=1e-4)
    assert np.allclose((out[1] * d).sum(0), 2 * (d * axis).sum(0) ** 2 - 1, atol=1e-5)


def test_turned_candidates_stay_unit_along_a_walk():
    """A guided walk turns each vertex's phase sample about the previous turned
    direction. Forward scattering (each sample near the axis, as HG 0.9 draws it) made
    an axis of length 1 + e give a turned direction of about 1 + 2e, so the error
    doubled at every vertex: rays of the wrong length (distances in the wrong units),
    then NaN/Inf samples in the camera-inside-a-cloud scene. 64 vertices, 256 walks,
    each step's axis the previous step's output; every direction stays unit."""
    rng = np.random.default_rng(5)
    n = 256
    axis = rng.normal(size=(3, n))
    axis = _vectors(axis / np.linalg.norm(axis, axis=0))
    for step in range(64):
        jitter = _vectors(0.05 * rng.normal(size=(3, n)))
        d = dr.normalize(axis + jitter)            # a forward-scattered phase sample
        axis = sampling.turned(axis, d, 4)[step % 3]
        length = np.array(dr.norm(axis))
        assert np.all(np.abs(length - 1.0) < 1e-5), (step, length.min(), length.max())


@pytest.mark.parametrize("lobe, r, symmetric", [(0, 0.85, True), (2, 0.85, True),
                                                 (2, 0.85, False), (2, 0.0, True)])
def test_resampling_estimates_the_phase_integral(lobe, r, symmetric):
    """One resampled vertex (3 phase candidates, turned or drawn, and ``lobe`` from a
    lobe of mean cosine ``r``; r = 0: a flat cell, so no lobe candidates): its weight
    times a test function ``h`` of the chosen direction has the mean ``int f h``
    (t-test, 2^20 vertices, alpha 1e-3, against a 1024 x 2048 midpoint quadrature), and
    it returns the phase function's value and pdf at that direction."""
    field = _field_with_lobe([0.3, -0.5, 0.8], r)
    phase = mi.load_dict({"type": "hg", "g": 0.7})
    ctx = mi.PhaseFunctionContext(None)
    c = np.array([-0.6, 0.2, 0.5]) / np.linalg.norm([-0.6, 0.2, 0.5])

    def h(d):
        return dr.exp(4.0 * (dr.dot(d, mi.Vector3f(*(float(x) for x in c))) - 1.0))

    def vertices(n):
        mei = dr.zeros(mi.MediumInteraction3f, n)
        mei.p = mi.Point3f(0.2, 0.3, 0.2)                 # in the lobe's cell
        mei.wi = dr.normalize(mi.Vector3f(0.5, 0.5, -0.7))
        mei.sh_frame = mi.Frame3f(mei.wi)
        return mei
    n = 1 << 20
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(11, n)
    mei = vertices(n)
    active = mi.Bool(True)
    first = phase.sample(ctx, mei, sampler.next_1d(), sampler.next_2d(), active)
    y, weight, pdf, f, _ = sampling.resample(field, phase, ctx, mei, sampler, 3, first,
                                              active, symmetric, lobe)
    value, p_y = phase.eval_pdf(ctx, mei, y)
    assert np.allclose(np.array(f), np.array(mi.Spectrum(value)).reshape(-1, n)[0], rtol=1e-4)
    assert np.allclose(np.array(pdf), np.array(p_y), rtol=1e-4)
    estimate = np.array(mi.Spectrum(weight)).reshape(-1, n)[0] * np.array(h(y))
    Z, _, d = _sphere_midpoints(1024, 2048)
    f_d = np.array(mi.Spectrum(phase.eval_pdf(ctx, vertices(Z.size), d)[0])).reshape(-1, Z.size)[0]
    exact = float(np.sum(f_d * np.array(h(d)), dtype=np.float64)) * 4 * np.pi / Z.size
    assert np.all(np.isfinite(estimate))
    t = scipy_stats.ttest_1samp(estimate, exact)
    assert t.pvalue > 1e-3, (estimate.mean(), exact, t)


#: guided renders of a case's scene with other settings: (scene, settings)
VARIANTS = {"lobe_candidates": ("lamp_under_sky", {"guiding_lobe": 2})}


@pytest.mark.parametrize("case", list(CASES) + list(VARIANTS))
def test_guided_renders_estimate_the_same_image(case, monkeypatch):
    """Guided (training passes included) against unguided ``volpath_delta``, 8 passes of 64
    spp each against 16 of 64, disjoint seeds; max_depth 16. The camera inside the cloud
    renders with the GPU's schedule (training merged into one 8-spp pass after the first:
    1, 8, 55 spp), the other cases with the unmerged one (1, 2, 4, 8, 49: the fixture).
    ``lobe_candidates``: resampling also draws 2 candidates from the lobes (15 of the 64
    cells concentrated enough after training)."""
    if case == "camera_inside":
        monkeypatch.setattr(guided_render, "min_pass_spp", lambda pixels: 8)
        assert guided_render.schedule(64, guided_render.TRAINING, 32 * 32, 8) == [1, 8, 55]
    name, settings = VARIANTS.get(case, (case, {}))
    key = f"guiding:{name}"
    a = cached_estimate(key, CASES[name], {**GUIDED, "max_depth": 16, **settings}, passes=8,
                        spp=64, seed=2000)
    b = cached_estimate(key, CASES[name], {"type": "volpath_delta", "max_depth": 16},
                        passes=16, spp=64)
    assert_same_expectation(a, b, f"guiding-{case}")


@pytest.mark.parametrize("t_end, lamps, g", [
    (0.7, (), None), (3.0, (), None), (math.inf, (), None),
    (3.0, ([0.1, 0.3, 0.1],), None), (math.inf, ([0.1, 0.3, 0.1], [0.9, 0.2, -0.5]), None),
    (3.0, ([0.1, 0.3, 0.1],), 0.75), (math.inf, ([0.1, 0.3, 0.1], [0.9, 0.2, -0.5]), -0.5),
    (0.7, ([0.1, 0.3, 0.1],), 0.95)])
def test_distance_pdf_is_the_density_of_its_samples(t_end, lamps, g):
    """Guided distances along a segment (a light grid of random cell values, some 0, some
    not yet learnt; with lamps, the equiangular components toward them too, weighted by a
    Henyey-Greenstein phase function of asymmetry ``g`` where it is given): chi-square
    test (alpha 1e-3) of 2^18 samples over 40 bins of [0, min(t_end, 4)] and the tail
    beyond, against the pdf integrated over each bin (1024 midpoints per bin); the pdf
    integrates to 1."""
    grid = LightGrid(mi.ScalarBoundingBox3f([-1, -1, -1], [1, 1, 1]), resolution=4,
                     lamps=list(lamps), phase_g=g)
    rng = np.random.default_rng(3)
    values = rng.random(grid.cells) * (rng.random(grid.cells) > 0.3)
    values[rng.random(grid.cells) < 0.2] = distance.UNKNOWN      # cells not yet learnt
    grid.mean = mi.Float(values.astype(np.float32))
    n, sigma = 1 << 18, 1.3
    # one lane's segment (width-1 arrays broadcast against the samples)
    ray = mi.Ray3f(mi.Point3f(-0.9, -0.4, 0.2), mi.Vector3f(0.8, 0.6, 0.0))
    seg = Segment(grid, ray, mi.Float(t_end), mi.Float(sigma), mi.Bool(True))
    u = mi.Float(((np.arange(n) + rng.random(n)) / n).astype(np.float32))
    t = np.array(seg.sample(u))
    assert np.all((t >= 0) & (t <= t_end))
    top = min(t_end, 4.0)
    edges = np.linspace(0.0, top, 41)
    # 1024 midpoints per bin: the phase-weighted lamp components jump at their pieces'
    # ends, next to equiangular's peak (64 midpoints missed a bin's mass by 2%)
    m = 1024
    mids = (edges[:-1, None] + (np.arange(m) + 0.5)[None, :] / m * (top / 40)).ravel()
    pdf = np.array(seg.pdf(mi.Float(mids.astype(np.float32))))
    mass = pdf.reshape(40, m).mean(axis=1) * (top / 40)
    mass = np.append(mass, max(0.0, 1.0 - mass.sum()))
    assert mass[:-1].sum() <= 1.0 + 2e-3
    if t_end <= 4.0:
        assert mass[:-1].sum() == pytest.approx(1.0, abs=2e-3)
    observed = np.append(np.histogram(t[t < top], edges)[0], np.sum(t >= top))
    keep = mass * n > 5
    expected = mass[keep] / mass[keep].sum() * observed[keep].sum()
    chi2 = float(((observed[keep] - expected) ** 2 / expected).sum())
    assert scipy_stats.chi2.sf(chi2, keep.sum() - 1) > 1e-3, chi2


def test_phase_weighted_lamp_density_follows_the_phase_function():
    """``PhaseLampSegment``: along a ray that passes a lamp, the density of the lamp's
    component over plain equiangular sampling's is the Henyey-Greenstein value toward the
    lamp (up to one constant and the piecewise-constant steps): with g = 0.75 the points
    before the closest approach (the lamp ahead, forward scattering) are drawn far more
    often than those after it; with g = -0.75 the other way round."""
    ray = mi.Ray3f(mi.Point3f(-2.0, 0.0, 0.0), mi.Vector3f(1.0, 0.0, 0.0))
    lamp, t_end, D = mi.Point3f(0.0, 0.3, 0.0), mi.Float(4.0), 0.3
    plain = equiangular.Segment(ray, t_end, lamp)
    # the middles of the pieces in angle (closest approach at t = 2)
    a, b = math.atan2(-2.0, D), math.atan2(2.0, D)
    theta = a + (np.arange(distance.LAMP_PIECES) + 0.5) * (b - a) / distance.LAMP_PIECES
    t = 2.0 + D * np.tan(theta)
    for g in (0.75, -0.75):
        seg = distance.PhaseLampSegment(ray, t_end, lamp, mi.Float(g))
        ratio = np.array(seg.pdf(mi.Float(t))) / np.array(plain.pdf(mi.Float(t)))
        # HG toward the lamp: the cosine between -d and the lamp's direction is sin(theta)
        hg = (1 - g * g) / (4 * np.pi * (1 + g * g + 2 * g * np.sin(theta)) ** 1.5)
        rel = ratio / hg
        assert rel.max() / rel.min() == pytest.approx(1.0, abs=1e-3), (g, rel)
        ahead = float(np.array(seg.pdf(mi.Float(1.0)))[0] / np.array(seg.pdf(mi.Float(3.0)))[0])
        assert ahead > 10 if g > 0 else ahead < 0.1, (g, ahead)


def test_common_hg_is_the_asymmetry_every_medium_shares():
    """``distance.common_hg``: one HG medium gives its g, an isotropic one 0, two HG media
    of different g or a medium whose phase function is not HG (SGGX) give None."""
    def media(*phases):
        return [mi.load_dict({"type": "homogeneous", "phase": ph}) for ph in phases]
    hg = {"type": "hg", "g": 0.6}
    assert distance.common_hg(media(hg)) == pytest.approx(0.6)
    assert distance.common_hg(media(hg, dict(hg))) == pytest.approx(0.6)
    assert distance.common_hg(media({"type": "isotropic"})) == 0.0
    assert distance.common_hg(media(hg, {"type": "hg", "g": 0.3})) is None
    sggx = {"type": "sggx", "S": {"type": "gridvolume", "grid": mi.VolumeGrid(
        np.array([1.0, 0.2, 0.5, 0.1, 0.0, 0.0], np.float32).reshape(1, 1, 1, 6))}}
    assert distance.common_hg(media(sggx)) is None


def test_lamps_are_small_lights_inside_a_medium():
    """``distance.lamps``: a small sphere light and a point light inside a fog ball are
    found (their centres); the same light outside the ball, a large one inside it, or
    more than MAX_LAMPS are not. With ``outside`` (an anisotropic phase function), lights
    outside the ball below SMALL_OUTSIDE_LAMP of its size count too, never as boxes."""
    def scene(center, radius, point=None, n=1, **kw):
        d = media_scene(homogeneous(1.0), env=0, as_dict=True)
        for i in range(n):
            d[f"light{i}"] = {"type": "sphere", "center": [center[0], center[1] + 0.01 * i,
                                                           center[2]],
                              "radius": radius, "emitter": {"type": "area"}}
        del d["light"]
        if point is not None:
            d["point"] = {"type": "point", "position": point}
        s = mi.load_dict(d)
        return distance.lamps(s, media_bounds(s), **kw)
    assert scene([0.2, 0.1, 0.0], 0.05) == [pytest.approx([0.2, 0.1, 0.0], abs=1e-5)]
    assert scene([0.2, 3.0, 0.0], 0.05) == []
    assert scene([0.2, 0.1, 0.0], 0.5) == []
    assert scene([0.2, 3.0, 0.0], 0.05, point=[0.0, -0.3, 0.2]) == \
        [pytest.approx([0.0, -0.3, 0.2], abs=1e-5)]
    assert scene([0.2, 0.1, 0.0], 0.02, n=distance.MAX_LAMPS + 1) == []
    # outside: the media_scene's light (radius 0.25, the ball's side 2: below 0.5 x 2)
    assert scene([1.6, 2.2, 1.2], 0.25, outside=True) == \
        [pytest.approx([1.6, 2.2, 1.2], abs=1e-5)]
    assert scene([1.6, 2.2, 1.2], 0.6, outside=True) == []
    assert scene([1.6, 2.2, 1.2], 0.25, outside=True, boxes=True) == []
    assert len(scene([0.2, 0.1, 0.0], 0.05, outside=True, boxes=True)) == 1


def test_lamp_boxes_hold_the_lamps_that_are_shapes():
    """``lamps(..., boxes=True)``: the bounds of a small sphere lamp (not of a point light),
    and ``LightGrid.on_lamp`` is true on its surface, false a little way off it."""
    d = media_scene(homogeneous(1.0), env=0, as_dict=True)
    d["lamp"] = {"type": "sphere", "center": [0.2, 0.1, 0.0], "radius": 0.05,
                 "emitter": {"type": "area"}}
    d["point"] = {"type": "point", "position": [0.0, -0.3, 0.2]}
    s = mi.load_dict(d)
    bounds = media_bounds(s)
    boxes = distance.lamps(s, bounds, boxes=True)
    assert len(boxes) == 1 and len(distance.lamps(s, bounds)) == 2
    assert np.allclose(boxes[0][0], [0.15, 0.05, -0.05], atol=1e-3)
    assert np.allclose(boxes[0][1], [0.25, 0.15, 0.05], atol=1e-3)
    grid = distance.LightGrid(bounds, lamps=distance.lamps(s, bounds), lamp_boxes=boxes)
    p = mi.Point3f([0.25, 0.2, 0.2, 0.3], [0.1, 0.15, 0.1, 0.1], [0.0, 0.0, 0.05, 0.0])
    assert np.array(grid.on_lamp(p)).tolist() == [True, True, True, False]


@pytest.mark.parametrize("bins", [16, 0])
def test_guided_surfaces_estimate_the_same_image(bins, monkeypatch):
    """``path_rr`` with ``guiding = surfaces`` (histograms, and one lobe per cell) against
    ``path_rr`` on the Cornell box (16 passes of 64 spp each, disjoint seeds, max_depth 8:
    roulette from depth 5 on, so its guided survival is tested too). 16 guided passes, not
    8: with 8, the lobes' block means near the light read |z| 3.8-4.4 against a threshold
    of 4.3 in the mono variant, their sign changing with the seed (the image-mean z -1.2 to
    0.1), when blocks' standard errors still came from the pixels as if independent: the
    scene's Gaussian filter correlates neighbouring pixels, and its blocks vary 1.7x more
    than that said (docs/validation.md, "Correlated pixels")."""
    # guided throughout: the Cornell box's share is below MIN_SHARE
    monkeypatch.setattr(guided_render, "MIN_SHARE", 0.0)
    key, make = loaded("cornell_box")
    a = cached_estimate(key, make, {"type": "path_rr", "max_depth": 8, "guiding": "surfaces",
                                    "guiding_bins": bins}, passes=16, spp=64, seed=2000)
    b = cached_estimate(key, make, {"type": "path_rr", "max_depth": 8}, passes=16, spp=64)
    assert_same_expectation(a, b, f"guiding-surfaces-cornell_box-bins{bins}")


def _fog_ball(res: int = 32, albedo: float = 0.9) -> mi.Scene:
    """A ball of homogeneous fog under a small light, nothing else: every path that
    gathers light has its first vertex in the fog."""
    scene = media_scene(homogeneous(2.0, albedo=albedo), sensor=camera(res=res), env=0,
                        as_dict=True)
    del scene["floor"]
    return mi.load_dict(scene)


def test_the_first_pass_measures_the_light_beyond_direct_light():
    """``GuidingReport.share`` (what the first pass's paths gathered beyond their first
    vertex's direct light, over all they gathered) against the same share from unguided
    renders by depth, (L - L_2) / (L - L_1) with ``L_d`` the image mean at ``max_depth``
    d (2: emission and single scattering, both halves of its MIS), in the fog ball where
    every lit path starts in the fog. Tolerance 0.015: the four first passes' shares
    spread by 0.004 (0.515-0.526 against 0.518 measured); counting what the first
    vertex's sampled direction hit directly as beyond, or its emitter sample, moves it
    by more."""
    scene = _fog_ball()
    L = {d: float(np.mean(render(scene, {"type": "volpath_delta", "max_depth": d},
                                 spp=4096, seed=5))) for d in (1, 2, -1)}
    expected = (L[-1] - L[2]) / (L[-1] - L[1])
    shares = []
    for seed in range(4):
        integrator = mi.load_dict(GUIDED)
        mi.render(scene, integrator=integrator, spp=1024, seed=seed)
        assert not integrator.guiding_report.skipped
        shares.append(integrator.guiding_report.share)
    assert abs(np.mean(shares) - expected) < 0.015, (shares, expected)


def test_guiding_goes_on_unguided_where_it_cannot_pay():
    """Below ``MIN_SHARE`` (the Cornell box, lit mostly directly: 0.26 at 128x128) a
    guided render's first pass is followed by one plain pass of the other samples, whose
    image it returns; the fog ball (0.52) is guided (on CUDA its passes merge to the same
    two counts, ``MIN_PASS_PATHS``: ``skipped`` tells them apart)."""
    key, make = loaded("cornell_box")
    integrator = mi.load_dict({"type": "path_rr", "guiding": "surfaces"})
    image = render(make(), integrator, spp=256, seed=3)
    report = integrator.guiding_report
    assert report.skipped and report.passes == [2, 254], report.passes
    assert 0 < report.share < guided_render.MIN_SHARE
    plain = render(make(), {"type": "path_rr"}, spp=256, seed=3)
    assert abs(image.mean() / plain.mean() - 1) < 0.02
    integrator = mi.load_dict(GUIDED)
    mi.render(_fog_ball(), integrator=integrator, spp=256, seed=3)
    assert not integrator.guiding_report.skipped


def test_guided_roulette_is_unbiased_and_bounded():
    """``RussianRoulette.apply`` with a guided path's ``gain``: the mean of the surviving
    throughput equals the throughput (t-test, alpha 1e-4, 2^20 lanes per case), and a
    survivor's largest channel stays at most 1 where the throughput was below the
    largest survival probability, as without guiding."""
    from mitsuba_plugins.path_vertex import RussianRoulette
    rr = RussianRoulette(rr_depth=1)
    n = 1 << 20
    rng = np.random.default_rng(3)
    for beta, gain in [(0.02, 20.0), (0.02, 0.05), (0.3, 1.0), (0.9, 3.0)]:
        b = mi.Spectrum(beta)
        out, alive = rr.apply(b, mi.Float(1.0), mi.UInt32(np.full(n, 2, np.uint32)),
                              mi.Float(rng.random(n).astype(np.float32)),
                              gain=mi.Float(np.full(n, gain, np.float32)))
        kept = np.where(np.array(alive), np.array(out)[0], 0.0)
        t = (kept.mean() - beta) / (kept.std(ddof=1) / np.sqrt(n))
        assert abs(t) < scipy_stats.norm.isf(0.5e-4), (beta, gain, kept.mean())
        assert kept.max() <= max(1.0, beta / rr.max_survival) * (1 + 1e-5), (beta, gain)


def test_small_images_render_in_one_plain_pass(monkeypatch):
    """Below ``MIN_TRAINING_PATHS`` paths of training (32x32 at 64 spp) a guided render
    is one plain pass; at 16x the sample count it trains first."""
    monkeypatch.setattr(guided_render, "MIN_TRAINING_PATHS", DEFAULT_MIN_TRAINING_PATHS)
    scene = media_scene(homogeneous(1.5, albedo=0.8), env=0)
    integrator = mi.load_dict(GUIDED)
    mi.render(scene, integrator=integrator, spp=64, seed=1)
    assert integrator.guiding_report.passes == [64]
    mi.render(scene, integrator=integrator, spp=1024, seed=1)
    assert len(integrator.guiding_report.passes) > 1
    assert sum(integrator.guiding_report.passes) == 1024


def test_training_passes_merge_where_a_pass_costs_more_than_its_paths():
    """``schedule``'s floor on the passes after the first (``MIN_PASS_PATHS``, the GPU's):
    doubling steps below it merge into one pass; where even that does not fit the training
    budget the first pass alone trains; a floor of 1 keeps the doubling."""
    schedule = guided_render.schedule
    assert schedule(64, 0.25, 128 * 128, 1) == [1, 2, 4, 8, 49]
    assert schedule(64, 0.25, 512 * 512, 8) == [1, 8, 55]
    assert schedule(64, 0.25, 128 * 128, 128) == [1, 63]
    assert schedule(1024, 0.25, 128 * 128, 128) == [8, 128, 888]
    for spp, m in [(64, 3), (256, 8), (1000, 100), (7, 2)]:
        plan = schedule(spp, 0.25, 1 << 20, m)
        assert sum(plan) == spp and all(n >= m for n in plan[1:-1]), plan
    floor = guided_render.MIN_PASS_PATHS["cuda" if mi.variant().startswith("cuda") else "llvm"]
    assert guided_render.min_pass_spp(128 * 128) == max(1, -(-floor // (128 * 128)))


def test_guided_open_furnace():
    """scenes/furnace_env.xml's analytic answer (its header: image mean 0.8), as
    tests/integrators/test_furnace.py checks every integrator."""
    img = render(load("furnace_env", res=32), GUIDED, spp=64, seed=5)
    assert_mean_equals(img, 0.8, "guiding-furnace")


def test_training_learns_where_the_light_is():
    """In a dense ball lit by one small light, the lobes of the cells nearest the light
    point toward it (mean cosine with the direction to the light above 0.5, over the
    cells with records on the light's side)."""
    scene = _dense_ball()
    integrator = mi.load_dict({**GUIDED, "max_depth": 32})
    mi.render(scene, integrator=integrator, spp=256, seed=1)
    field = integrator.guiding_report.field
    light = np.array([1.6, 2.2, 1.2])
    r = field.resolution
    kappa = np.array(field.kappa)
    mu = np.stack([np.array(m) for m in field.mu], axis=1)
    cosines = []
    for idx in np.nonzero(kappa > 0)[0]:
        z, y, x = idx // (r * r), (idx // r) % r, idx % r
        centre = (np.array([x, y, z]) + 0.5) / r * 2.0 - 1.0
        if centre @ light > 0:
            to_light = (light - centre) / np.linalg.norm(light - centre)
            cosines.append(mu[idx] @ to_light)
    assert len(cosines) >= 4 and np.mean(cosines) > 0.5, cosines
    assert integrator.guiding_report.cells_guided == len(np.nonzero(kappa > 0)[0])


def test_a_scene_without_media_renders_in_one_pass():
    scene = load("cornell_box", res=16)
    integrator = mi.load_dict(GUIDED)
    mi.render(scene, integrator=integrator, spp=64)
    assert integrator.guiding_report.passes == [64]


@pytest.mark.parametrize("name, value, bound", [
    ("guiding", "surfaces", "off | volumes"),
    ("guiding_candidates", 0, "[1, 32]"),
    ("guiding_lobe", 33, "[0, 32]"),
    ("guiding_training", 0.95, "<= 0.9"),
    ("guiding_resolution", 64, "[1, 32]"),
    ("guiding_roulette", 1.5, "<= 1"),
])
def test_bad_guiding_parameters_are_refused(name, value, bound):
    """The message names the parameter and its allowed range."""
    with pytest.raises(Exception) as info:
        mi.load_dict({**GUIDED, name: value})
    message = str(info.value)
    assert f"parameter '{name}'" in message and "allowed" in message and bound in message


@pytest.mark.parametrize("name, value, bound", [
    ("guiding", "volumes", "off | surfaces"),
    ("guiding_fraction", 0.95, "<= 0.9"),
    ("guiding_bins", 65, "[0, 64]"),
])
def test_bad_surface_guiding_parameters_are_refused(name, value, bound):
    with pytest.raises(Exception) as info:
        mi.load_dict({"type": "path_rr", "guiding": "surfaces", name: value})
    message = str(info.value)
    assert f"parameter '{name}'" in message and "allowed" in message and bound in message


def test_memory_is_bounded_and_reported():
    """The largest field of lobes allowed (32^3 cells) stays under the 64 MiB cap; the
    histograms' size is checked when the plugin loads, naming both parameters."""
    field = GuidingField(mi.ScalarBoundingBox3f([0, 0, 0], [1, 1, 1]), resolution=32)
    assert field.memory() < 64 << 20
    assert math.isclose(field.memory() / 2**20, float(field.describe().split(", ")[1].split()[0]),
                        rel_tol=0.01)
    field = HistogramField(mi.ScalarBoundingBox3f([0, 0, 0], [1, 1, 1]), resolution=8)
    assert math.isclose(field.memory() / 2**20, float(field.describe().split(", ")[1].split()[0]),
                        rel_tol=0.01)
    with pytest.raises(Exception, match="guiding_resolution.*guiding_bins.*64 MiB"):
        mi.load_dict({"type": "path_rr", "guiding": "surfaces", "guiding_resolution": 32})


def test_benchmarks_log_whether_each_timed_render_was_guided(monkeypatch):
    """The equal-time benchmarks record, per timed run of a guided configuration, its
    passes and whether it trained and guided (``benchmarks.dense.guiding_summary``), and
    their tables say where not every run was guided: at equal time a guided render's
    sample count can fall below ``MIN_TRAINING_PATHS`` paths of training, and it then
    renders one plain pass."""
    from benchmarks import dense
    monkeypatch.setattr(guided_render, "MIN_TRAINING_PATHS", DEFAULT_MIN_TRAINING_PATHS)
    scene = media_scene(homogeneous(1.5, albedo=0.8), env=0)
    integrator = mi.load_dict(GUIDED)
    runs = []
    for spp in (64, 1024):
        mi.render(scene, integrator=integrator, spp=spp, seed=1)
        runs.append(dense.guiding_summary(integrator.guiding_report))
    assert runs[0] == {"passes": [64], "share": None, "guided": False}
    assert runs[1]["guided"] and sum(runs[1]["passes"]) == 1024
    assert 0 < runs[1]["share"] <= 1
    assert dense.guided_runs_note({"guiding_runs": runs}) == " (guided in 1 of 2 runs)"
    assert dense.guided_runs_note({"guiding_runs": runs[1:]}) == ""
    assert dense.guided_runs_note({}) == ""


def test_dense_media_beside_thin_ones_steer_no_guided_points():
    """A homogeneous medium whose optical depth across a light-grid cell exceeds
    ``MAX_CELL_DEPTH`` takes no guided points and records nothing into the light grid
    (``LightGrid.takes``): after a guided render of a dense cube beside a thin one, the
    cells wholly inside the dense cube hold no records and those inside the thin one do.
    Recorded there, the dense cube's dark interior was learnt for the cells it shares with
    the thin cube."""
    integrator = mi.load_dict(GUIDED)
    mi.render(_cube_pair(), integrator=integrator, spp=64, seed=4)
    light = integrator.guiding_report.light
    assert light is not None
    r = light.resolution
    lo = np.array(light.lo)
    size = 1.0 / np.array(light.inv_size)
    idx = np.arange(r ** 3)
    ijk = np.stack([idx % r, (idx // r) % r, idx // (r * r)], 1)
    a, b = lo + ijk * size / r, lo + (ijk + 1) * size / r      # each cell's box
    counts = light.sums[:, 1]

    def inside(box_lo, box_hi):
        return np.all((a >= box_lo) & (b <= box_hi), axis=1)
    in_dense = inside(np.array([-1.05, -0.5, -0.5]), np.array([-0.05, 0.5, 0.5]))
    in_thin = inside(np.array([0.05, -0.5, -0.5]), np.array([1.05, 0.5, 0.5]))
    assert in_dense.sum() > 20 and in_thin.sum() > 20
    assert counts[in_dense].sum() == 0, counts[in_dense].sum()
    assert (counts[in_thin] > 0).mean() > 0.9
    sigma = np.array([300.0, 1.0], np.float32)
    takes = np.array(light.takes(mi.Bool([True, True]), mi.Spectrum(mi.Float(sigma))))
    assert list(takes) == [False, True]
    assert list(np.array(light.takes(mi.Bool([False]), mi.Spectrum(mi.Float(1e6))))) == [True]


def test_small_images_merge_their_training_passes_on_the_cpu():
    """On the CPU every pass after the first traces at least 2^15 paths
    (``MIN_PASS_PATHS``): 32x32 at 256 spp trains in passes of 2 and 32 spp, 64x64 at 64
    spp in 1 and 8; from 128x128 the doubling schedule is unchanged."""
    schedule = guided_render.schedule

    def floor(pixels):        # min_pass_spp on the LLVM backend, whichever this variant's
        return max(1, -(-DEFAULT_CPU_MIN_PASS_PATHS // pixels))
    assert DEFAULT_CPU_MIN_PASS_PATHS == 1 << 15
    assert schedule(256, 0.25, 32 * 32, floor(32 * 32)) == [2, 32, 222]
    assert schedule(64, 0.25, 64 * 64, floor(64 * 64)) == [1, 8, 55]
    assert schedule(64, 0.25, 128 * 128, floor(128 * 128)) == [1, 2, 4, 8, 49]


def test_surface_histograms_learn_light_times_cosine():
    """``path_rr``'s surface records are ``f cos Li / p`` (``path_loop.SURFACE_PRODUCT``):
    a white floor (normal +z) under a constant sky, one bounce (max_depth 2), learns bins
    in proportion to ``cos theta`` times the BSDF side's MIS weight (the power heuristic
    against the sky's uniform sphere sample), ``w = 16 z^2 / (16 z^2 + 1)``. The summed
    bins of the band ``z`` in [0.75, 1] over those of [0, 0.25] predict 21.1, the ratio of
    ``int z w dz`` over the two bands; records of ``Li`` alone (the field before) give
    that of ``int w dz``, 4.3 (measured: 21.3 now, 4.32 before). Within 15%: two bands
    of 32 bins each from the first pass's 16,384 paths (4 spp); the rest renders as one
    plain pass, since no light lies beyond the first vertex's direct light."""
    scene = mi.load_dict({
        "type": "scene",
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"}},
        "sky": {"type": "constant"},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 64, "height": 64},
                   "sampler": {"type": "independent"}}})
    integrator = mi.load_dict({"type": "path_rr", "max_depth": 2, "guiding": "surfaces",
                               "guiding_training": 0.9})
    mi.render(scene, integrator=integrator, spp=512, seed=3)
    field = integrator.guiding_report.field
    n = field.bins
    hist = np.asarray(field.hist).reshape(field.cells, n, n).sum(axis=(0, 2))  # per z band

    def band(lo, hi):
        return hist[int((lo + 1) * n / 2):int((hi + 1) * n / 2)].sum()
    from scipy.integrate import quad

    def w(z):       # the power heuristic's BSDF side: (cos / pi)^2 against (1 / 4 pi)^2
        return 16 * z * z / (16 * z * z + 1)

    def ratio(f):
        return quad(f, 0.75, 1)[0] / quad(f, 0, 0.25)[0]
    product, light = ratio(lambda z: z * w(z)), ratio(w)
    measured = band(0.75, 1) / band(0, 0.25)
    assert hist[: n // 2].sum() == 0, "records below the floor"
    assert abs(measured / product - 1) < 0.15, (measured, product, light)


# -- learnt next-event estimation (path_rr's guiding_nee) --------------------------------
def test_emitter_samples_taken_with_any_probability_estimate_the_same_image(monkeypatch):
    """Every side of every cell takes emitter samples with probability 0.3 (instead of
    the learnt one): weighted by 1 / 0.3, and in the MIS weights of both techniques as a
    density 0.3 p_l, the guided Cornell box still estimates the unguided image (the same
    z-tests and passes as ``test_guided_surfaces_estimate_the_same_image``). Measured to
    fail: with the emission's MIS weight left at p_l (3 blocks beyond |t| 4.43, image-mean
    z -2.4) and without the 1 / q (image-mean z -140)."""
    monkeypatch.setattr(guided_render, "MIN_SHARE", 0.0)
    monkeypatch.setattr(GuidingField, "nee_probabilities",
                        lambda self: np.full(self.cells * NEE_SIDES, 0.3))
    key, make = loaded("cornell_box")
    a = cached_estimate(f"{key}:nee-q0.3", make, {"type": "path_rr", "max_depth": 8,
                                                  "guiding": "surfaces"},
                        passes=16, spp=64, seed=3000)
    b = cached_estimate(key, make, {"type": "path_rr", "max_depth": 8}, passes=16, spp=64)
    assert_same_expectation(a, b, "guiding-nee-q0.3-cornell_box")


def test_emitter_sampling_probability_follows_what_the_samples_bring(monkeypatch):
    """After a guided render of the Cornell box (64x64, 256 spp), every side of a cell that
    faces down (the ceiling, behind its light's plane: its emitter samples find nothing)
    takes them with ``NEE_MIN``, and the floor's sides (lit directly, most of the image's
    light) mostly with 1 (measured: median 1; with squared light counted in absolute
    terms instead of relative to its pixel, the light seen directly made the floor's
    median 0.17)."""
    monkeypatch.setattr(guided_render, "MIN_SHARE", 0.0)
    integrator = mi.load_dict({"type": "path_rr", "max_depth": 8, "guiding": "surfaces"})
    mi.render(load("cornell_box", res=64), integrator=integrator, spp=256, seed=1)
    field = integrator.guiding_report.field
    q = np.array(field.nee).reshape(field.cells, NEE_SIDES)
    known = field.nee_sums[:, 1].reshape(field.cells, NEE_SIDES) >= MIN_RECORDS
    down, up = 3, 2                                    # -y and +y (GuidingField.nee_index)
    assert known[:, down].sum() >= 16 and known[:, up].sum() >= 16
    assert np.all(q[known[:, down], down] == np.float32(NEE_MIN)), q[known[:, down], down]
    assert np.median(q[known[:, up], up]) == 1.0, q[known[:, up], up]


def test_emitter_sampling_probability_is_the_rule_of_least_variance_times_time():
    """``GuidingField.nee_probabilities`` on sums set by hand: ``q = sqrt(a n / (rho V))``
    clamped to [NEE_MIN, 1] (``a`` a side's mean weighted squared contribution, ``n`` the
    last pass's emitter-sample vertices per path, ``V`` its paths' weighted mean squared
    light), 1 where a side has too few vertices or the pass found no light; and
    ``nee_index`` names the side a normal faces."""
    field = GuidingField(mi.ScalarBoundingBox3f([0, 0, 0], [1, 1, 1]), resolution=1)
    n, V = 4.0, 2.0
    field.flow = np.array([0.0, 0.0, V * 1000, 1000.0])
    field.nee_per_path = n
    A = np.array([0.25 * NEE_SHARE * V / n, 0.0, 100.0, 1e-9, 0.04 * NEE_SHARE * V / n, 1.0])
    count = np.array([100, 100, 100, 100, 100, MIN_RECORDS - 1], np.float64)
    field.nee_sums = np.stack([A * count, count], axis=1)
    q = field.nee_probabilities()
    assert q == pytest.approx([0.5, NEE_MIN, 1.0, NEE_MIN, 0.2, 1.0])
    field.flow = np.zeros(4)
    assert np.all(field.nee_probabilities() == 1.0)
    normals = mi.Vector3f([1, -1, 0, 0, 0, 0, 0.6], [0, 0, 1, -1, 0, 0, -0.8],
                          [0, 0, 0, 0, 1, -1, 0])
    index = GuidingField.nee_index(mi.UInt32(2), normals)
    assert np.array(index).tolist() == [12, 13, 14, 15, 16, 17, 15]


def test_pixel_weights_are_smoothed_inverse_squares():
    """``guided_render.pixel_weights``: row-major, ``1 / v^2`` of the image smoothed by
    the box; a black pixel takes its neighbours' smoothed value, a black image the
    floor's (no division by zero)."""
    image = np.ones((8, 10, 3))
    image[:, 5:] = 2.0                                 # the right half twice as bright
    w = np.array(guided_render.pixel_weights(image)).reshape(8, 10)
    assert w[:, :3] == pytest.approx(1.0) and w[:, 8:] == pytest.approx(0.25)
    image[4, 1] = 0.0                                  # one black pixel: 24 / 25 around it
    w = np.array(guided_render.pixel_weights(image)).reshape(8, 10)
    assert w[4, 1] == pytest.approx((25 / 24) ** 2)
    assert np.all(np.isfinite(np.array(guided_render.pixel_weights(np.zeros((4, 4, 3))))))
