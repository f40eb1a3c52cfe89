"""Dense-media benchmark family (issue 16): where volpath_delta's time and variance go
on dense smoke and clouds, and its efficiency against Mitsuba's volpath.

The family is generated here (no data files): smooth plumes and cumulus-like grids
(max/mean 3-20, optical depth 2-50 through the middle of the box, albedo 0.8-0.999,
HG g 0-0.9) under three lightings -- ``area`` (a small sphere light plus a dim sky),
``sun`` (a directional light plus a sky) and ``env`` (an environment map only) -- and
homogeneous cubes with extinction 1e2-1e4. All render with max_depth -1 (Mitsuba's
default) and rr_depth 5.

1. ``efficiency``: equal time against volpath. Both integrators are compiled first, the
   time per sample of each measured, then volpath renders ``--spp`` and each variant of
   ours the spp that takes as long; ``--runs`` alternating renders each, seeds 0..runs-1.
   relMSE (docs/method.md section 1) against a reference (:data:`REFERENCE`, ``--ref-spp``;
   its own noise adds the same expected error to both sides, so ratios are conservative;
   given the reference as a ``stats.Estimate`` (:func:`reference_estimate`, as
   ``benchmarks.guiding`` does), that error, ``compare.reference_floor``, is subtracted,
   and the raw figures are kept beside); efficiency = 1 / (mean relMSE x median time).
   The 90% interval of each ratio is a bootstrap over the runs (both sides resampled).
2. ``profile``: per camera path, counted in our kernels (``instrument.counting``):
   ray intersections, shadow rays, medium and surface vertices, null collisions in
   flights and tentative collisions on shadow rays (each is one density lookup; real
   collisions add one each); time per sample of both integrators.
3. ``variance``: relative variance per sample (mean over pixels of variance / (mean^2 +
   0.01), times spp) of volpath_delta, whole and split: by depth (max_depth 1, 2, 4, 8:
   the variance of the truncated estimator), by term (emitter sampling alone, emission
   found by phase/BSDF sampling alone) and by shadow-ray estimator. Sections 2 and 3
   profile the defaults before issue 16 (``old_default``), which decided what to build.

``python3 -m benchmarks.dense --out benchmarks/results/dense_profile`` gave the profile;
``python3 -m benchmarks.dense --no-profile --variants A,B,...`` compares configurations of
:data:`VARIANTS` at equal time (the defaults' choice, ``benchmarks/results/dense.md``).
"""
from __future__ import annotations

import argparse
import datetime
import statistics
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before drjit loads
import mitsuba as mi
import numpy as np

from benchmarks.harness import alternate, device_model, timed_render
from benchmarks.volpath_delta import smooth_field
from mitsuba_plugins.registry import default_variant  # noqa: E402

VARIANT = default_variant()
mi.set_variant(VARIANT)
from mitsuba_plugins import instrument, output  # noqa: E402
from mitsuba_plugins.tracking.majorant import DEFAULT_RESOLUTION  # noqa: E402
from mitsuba_plugins.tools import stats  # noqa: E402
from mitsuba_plugins.tools.compare import reference_floor  # noqa: E402
from mitsuba_plugins.validity import take_invalid_samples  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BUILTIN = {"type": "volpath"}
#: Configurations of ours compared on the family (``--variants``).
VARIANTS = {
    # Every entry spells out what it compares, so that a change of defaults cannot
    # change what an entry measures (the defaults' own entry excepted).
    "volpath_delta": {"type": "volpath_delta"},          # the defaults
    "old_default": {"type": "volpath_delta", "transmittance": "track_length",  # before 16
                    "rr_max_survival": 0.95, "medium": {"majorant_resolution": 16}},
    "majorant16": {"type": "volpath_delta", "transmittance": "residual",
                   "rr_max_survival": 0.99, "medium": {"majorant_resolution": 16}},
    "track_length_rr0.99": {"type": "volpath_delta", "transmittance": "track_length",
                            "rr_max_survival": 0.99},
    "ratio_rr0.99": {"type": "volpath_delta", "transmittance": "ratio", "rr_max_survival": 0.99},
    "residual_rr0.95": {"type": "volpath_delta", "transmittance": "residual",
                        "rr_max_survival": 0.95},
    "residual_rr0.999": {"type": "volpath_delta", "transmittance": "residual",
                         "rr_max_survival": 0.999},
    # issue 29: caps between Mitsuba's 0.95 and the default 0.99
    **{f"residual_rr{c:g}": {"type": "volpath_delta", "transmittance": "residual",
                             "rr_max_survival": c} for c in (0.97, 0.98)},
    "decomposition": {"type": "volpath_delta", "free_flight": "decomposition",   # issue 25
                      "transmittance": "residual", "rr_max_survival": 0.99},
    # issue 29: Russian roulette between a shadow ray's pieces (0: off, before 29)
    **{f"shadow_rr{t:g}": {"type": "volpath_delta", "transmittance": "residual",
                            "rr_max_survival": 0.99, "shadow_roulette": t}
       for t in (0.0, 0.1, 0.2, 0.5)},
    # issue 29: equiangular sampling toward point and spot lights (experiment)
    "equiangular": {"type": "volpath_delta", "equiangular": True},
    # issue 47: path guiding in media (its defaults)
    "guided": {"type": "volpath_delta", "guiding": "volumes"},
    "volpath_raymarch": {"type": "volpath_raymarch"},   # biased: see ``--bias``
    "rm_rr0.999": {"type": "volpath_raymarch", "rr_max_survival": 0.999},
}
#: A variant's ``medium`` entry holds properties of the grid medium (not the integrator).

#: The reference's integrator: unbiased and with bounded path weights (a survival cap
#: above albedo^2 keeps the second moment finite), so no rare firefly dominates it.
REFERENCE = {"type": "volpath_delta", "rr_max_survival": 0.999, "transmittance": "residual",
             "shadow_roulette": 0.0}


@dataclass(frozen=True)
class Case:
    name: str
    shape: str             # plume | cumulus | homogeneous
    max_over_mean: float   # of the density grid (1 for homogeneous)
    tau: float             # optical depth through the middle of the box (sigma_t * 2)
    albedo: float
    g: float
    light: str             # area | sun | env


FAMILY = [
    Case("plume_area", "plume", 8, 5, 0.95, 0.3, "area"),
    Case("plume_sun", "plume", 15, 20, 0.99, 0.7, "sun"),
    Case("plume_env", "plume", 4, 2, 0.8, 0.0, "env"),
    Case("plume_sun_thick", "plume", 20, 50, 0.999, 0.85, "sun"),
    Case("cumulus_area", "cumulus", 3, 10, 0.99, 0.5, "area"),
    Case("cumulus_sun", "cumulus", 5, 50, 0.999, 0.9, "sun"),
    Case("cumulus_env", "cumulus", 3, 20, 0.95, 0.2, "env"),
    Case("cumulus_area_thin", "cumulus", 10, 2, 0.8, 0.9, "area"),
    Case("homogeneous_1e2", "homogeneous", 1, 2e2, 0.99, 0.5, "sun"),
    Case("homogeneous_1e3", "homogeneous", 1, 2e3, 0.999, 0.7, "env"),
    Case("homogeneous_1e4", "homogeneous", 1, 2e4, 0.999, 0.0, "area"),
]


# -- generated media ------------------------------------------------------------------------
def _shape(shape: str, n: int, seed: int) -> np.ndarray:
    z, y, x = np.meshgrid(*(np.linspace(0, 1, n),) * 3, indexing="ij")
    noise = smooth_field(n, seed)
    noise = 0.55 + 0.45 * (noise - noise.min()) / (noise.max() - noise.min())
    if shape == "plume":        # a column rising from the floor, widening and bending
        cx, cz = 0.5 + 0.12 * np.sin(3.0 * y), 0.5 + 0.08 * np.cos(2.0 * y)
        s = 0.07 + 0.22 * y
        f = np.exp(-((x - cx) ** 2 + (z - cz) ** 2) / (2 * s ** 2)) * np.clip(4 * y, 0, 1)
    else:                       # cumulus: a flat-based heap of blobs
        rng = np.random.default_rng(seed)
        f = np.zeros_like(x)
        for _ in range(9):
            c = rng.uniform([0.25, 0.3, 0.25], [0.75, 0.6, 0.75])
            r = rng.uniform(0.12, 0.22)
            f = np.maximum(f, np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)
                                     / (2 * r ** 2)))
        f *= np.clip((y - 0.2) / 0.1, 0, 1)
    return f * noise + 1e-4


def density(shape: str, max_over_mean: float, n: int = 48, seed: int = 5) -> np.ndarray:
    """Density on n^3 with the given max/mean: the shape raised to the power that gives
    it (bisection), normalised so that the mean optical depth of the three axis lines
    through the centre is 1 per unit length."""
    base = _shape(shape, n, seed)
    lo, hi = 0.0, 16.0
    for _ in range(50):
        p = 0.5 * (lo + hi)
        f = base ** p
        lo, hi = (p, hi) if f.max() / f.mean() < max_over_mean else (lo, p)
    f = base ** (0.5 * (lo + hi))
    c = n // 2
    line = (f[:, c, c].mean() + f[c, :, c].mean() + f[c, c, :].mean()) / 3
    return (f / line).astype(np.float32)


def medium(case: Case, tmp: Path, extra: dict | None = None) -> dict:
    common = {"albedo": case.albedo, "phase": {"type": "hg", "g": case.g}}
    if case.shape == "homogeneous":
        return {"type": "homogeneous", "sigma_t": case.tau / 2, **common}
    common.update(extra or {})
    path = tmp / f"{case.shape}_{case.max_over_mean:g}.npy"
    if not path.exists():
        np.save(path, density(case.shape, case.max_over_mean))
    return {"type": "grid_medium", "filename": str(path), "scale": case.tau / 2,
            "to_world": mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2), **common}


def sky(tmp: Path, res: int = 64) -> str:
    """An environment map: a blue-to-white gradient sky, a dark ground, a sun-like spot;
    written to an EXR file in ``tmp`` (an ``envmap`` given a Bitmap built from a temporary
    numpy array failed once to load, "basic_string::_M_create"), its path returned."""
    v, u = np.meshgrid((np.arange(res // 2) + 0.5) / (res // 2), (np.arange(res) + 0.5) / res,
                       indexing="ij")
    up = np.cos(np.pi * v)[..., None]
    img = np.where(up > 0, 0.3 * np.array([0.5, 0.7, 1.0]) + 0.4 * (1 - up),
                   0.05 * np.array([1.0, 0.9, 0.8]))
    spot = np.exp(-((u - 0.3) ** 2 + (v - 0.3) ** 2) / (2 * 0.03 ** 2))[..., None]
    path = tmp / "sky.exr"
    if not path.exists():
        mi.Bitmap(np.ascontiguousarray(img + 60.0 * spot, dtype=np.float32)).write(str(path))
    return str(path)


def scene(case: Case, res: int, tmp: Path, extra: dict | None = None) -> mi.Scene:
    """The case's scene; ``extra``: properties added to its grid medium (load one scene
    per case and vary the medium with :func:`set_medium`)."""
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": 40,
                    "to_world": mi.ScalarTransform4f().look_at([0.2, 0.9, 3.2], [0, 0, 0],
                                                               [0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": res, "height": res,
                             "rfilter": {"type": "box"}},
                    "sampler": {"type": "independent", "sample_count": 16}},
         "box": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium(case, tmp, extra)}}
    floor = {"type": "rectangle", "bsdf": {"type": "diffuse",
                                           "reflectance": {"type": "rgb", "value": 0.5}},
             "to_world": mi.ScalarTransform4f().translate([0, -1.0, 0]).rotate(
                 [1, 0, 0], -90).scale(3)}
    if case.light == "area":
        d.update(floor=floor,
                 sky={"type": "constant", "radiance": {"type": "rgb", "value": 0.03}},
                 light={"type": "sphere", "center": [2.0, 2.5, 1.5], "radius": 0.12,
                        "emitter": {"type": "area", "radiance": {"type": "rgb",
                                                                  "value": 150.0}}})
    elif case.light == "sun":
        d.update(floor=floor,
                 sky={"type": "constant", "radiance": {"type": "rgb", "value": [0.1, 0.15, 0.25]}},
                 sun={"type": "directional", "direction": [-0.6, -1.0, -0.4],
                      "irradiance": {"type": "rgb", "value": 3.0}})
    else:
        d.update(env={"type": "envmap", "filename": sky(tmp)})
    return mi.load_dict(d)


# -- measurements -----------------------------------------------------------------------------
def reference_estimate(scene, spp: int, variant: dict = REFERENCE,
                       seed: int = 7 * 10 ** 6) -> stats.Estimate:
    """The reference: the mean of renders of 256 spp (seeds ``seed + i``), with its
    per-pixel standard error from their spread (infinite with a single render)."""
    integ = integrator(variant)
    chunk = min(spp, 256)
    return stats.Estimate.from_passes([timed_render(scene, integ, chunk, seed=seed + i)[1]
                                       for i in range(max(1, spp // chunk))], chunk)


def reference(scene, spp: int, variant: dict = REFERENCE, seed: int = 7 * 10 ** 6) -> np.ndarray:
    return reference_estimate(scene, spp, variant, seed).mean


def bias(scene, variants: dict, spp: int, ref) -> dict:
    """The bias of each variant, from ``spp`` samples of it (seeds unlike the reference's):
    the relative error of the image's total (``energy``) and the relMSE against the
    reference, next to ``noise_floor``, the relMSE of as many samples of the unbiased
    reference integrator (so relMSE - noise_floor estimates bias^2 plus the variant's
    extra noise)."""
    ref_sum = float(np.sum(ref))
    unbiased = reference(scene, spp, seed=9 * 10 ** 6)
    out = {"noise_floor": stats.rel_mse(unbiased, ref),
           "noise_floor_energy": float(np.sum(unbiased)) / ref_sum - 1}
    for k, v in variants.items():
        img = reference(scene, spp, v, seed=8 * 10 ** 6)
        out[k] = {"rel_mse": stats.rel_mse(img, ref), "energy": float(np.sum(img)) / ref_sum - 1}
    return out


def bootstrap_ratio(ours, builtin, n: int = 2000, seed: int = 1) -> tuple:
    """5% and 95% quantiles of mean(builtin relMSE) / mean(ours relMSE), runs resampled."""
    rng = np.random.default_rng(seed)
    a, b = np.asarray(ours), np.asarray(builtin)
    r = [b[rng.integers(0, len(b), len(b))].mean() / a[rng.integers(0, len(a), len(a))].mean()
         for _ in range(n)]
    return float(np.quantile(r, 0.05)), float(np.quantile(r, 0.95))


def integrator(variant: dict):
    return mi.load_dict({k: v for k, v in variant.items() if k != "medium"})


def set_medium(scene, extra: dict | None) -> None:
    """Give the scene's grid medium a variant's ``medium`` properties (only
    ``majorant_resolution``; absent: the automatic choice), in place. One medium instance
    per scene on purpose: every live medium joins the virtual-call domain of the
    kernels, and with 8 scenes of this family loaded volpath ran 1.8x slower (ours 1.3x),
    which would skew any comparison between scenes loaded side by side."""
    extra = dict(extra or {})
    cells = extra.pop("majorant_resolution", None)
    assert not extra, f"unsupported medium properties {extra}"
    for shape in scene.shapes():
        m = shape.interior_medium()
        wanted = (cells or DEFAULT_RESOLUTION, cells is None)
        # only on a change: a rebuild may hand Dr.Jit scalars of another alignment, and
        # the next render then compiles a new kernel (measured: 0.9 s on a 0.04 s render)
        if m is not None and hasattr(m, "auto_cells") and (m.cells, m.auto_cells) != wanted:
            m.cells, m.auto_cells = wanted
            m.parameters_changed()


def time_per_sample_ratio(e: dict, k: str) -> float:
    """Measured time per sample of ``k`` over volpath's: median time of the timed renders
    over their spp (``s_per_spp`` is the calibration's, which one slowed render can
    skew: tuning18 of dense_heldout.py, calibration 2.56, measured 0.66)."""
    return (e[k]["median_s"] / e[k]["spp"]) / (e["builtin"]["median_s"] / e["builtin"]["spp"])


def render_variant(scene, integ, variant, spp: int, seed: int):
    set_medium(scene, (variant or {}).get("medium"))
    return timed_render(scene, integ, spp, seed)


def guiding_summary(report) -> dict:
    """What one guided render did (``guided_render.GuidingReport``): its passes, the first
    pass's share of light beyond the first vertex's direct light, and whether it went on
    unguided (one plain pass: too few training paths; or the share below ``MIN_SHARE``)."""
    return {"passes": list(report.passes), "share": report.share,
            "guided": len(report.passes) > 1 and not report.skipped}


def guided_runs_note(e: dict) -> str:
    """`` (guided in a of b runs)`` for a configuration whose renders were not all guided
    (``equal_time``'s ``guiding_runs``), else ``""``."""
    runs = e.get("guiding_runs")
    if not runs:
        return ""
    done = sum(r["guided"] for r in runs)
    return "" if done == len(runs) else f" (guided in {done} of {len(runs)} runs)"


def equal_time(scene, variants: dict, spp: int, runs: int, ref, builtin: dict = BUILTIN) -> dict:
    integ = {"builtin": mi.load_dict(builtin), **{k: integrator(v) for k, v in variants.items()}}
    variant = {"builtin": None, **variants}
    per_spp = {}
    for k, i in integ.items():     # compile, then time three renders (median: one render
        render_variant(scene, i, variant[k], spp, seed=10 ** 6)    # slowed 5x by the machine
        per_spp[k] = statistics.median(                            # set a wrong spp, issue 29)
            render_variant(scene, i, variant[k], spp, seed=10 ** 6 + 1 + j)[0]
            for j in range(3)) / spp
    n = {k: max(1, int(round(spp * per_spp["builtin"] / per_spp[k]))) for k in integ}
    for k, i in integ.items():       # the sample count is a literal of every kernel: compile
        render_variant(scene, i, variant[k], n[k], seed=10 ** 6 + 2)    # at n[k] first
        take_invalid_samples(i)      # the timed runs' NaN/Inf samples only, below
    guided = {k: [] for k in integ}      # per timed run of a guided render: what it did

    def timed(k, run):
        out = render_variant(scene, integ[k], variant[k], n[k], seed=run)
        report = getattr(integ[k], "guiding_report", None)
        if report is not None:
            guided[k].append(guiding_summary(report))
        return out
    times, images = alternate(integ, runs, timed)
    for k in integ:
        assert all(np.isfinite(img).all() for img in images[k]), f"{k}: non-finite pixels"
    # NaN/Inf samples our plugins zeroed and counted in the timed runs (None: the built-in,
    # which does not count; its pixels are checked finite above)
    invalid = {k: take_invalid_samples(i) for k, i in integ.items()}
    for k, count in invalid.items():
        if count:
            print(f"warning: {k}: {count} NaN/Inf samples in {runs} renders", flush=True)
    # against a stats.Estimate of several renders: its own relative MSE subtracted
    # (compare.reference_floor, as `mitsuba-plugins compare` does), the raw figure beside it
    mean = ref.mean if isinstance(ref, stats.Estimate) else ref
    floor = reference_floor(ref) if isinstance(ref, stats.Estimate) and ref.passes > 1 else None
    raw = {k: [stats.rel_mse(img, mean) for img in images[k]] for k in integ}
    errors = {k: [e - (floor or 0.0) for e in raw[k]] for k in integ}
    out = {}
    for k in integ:
        t, e = statistics.median(times[k]), float(np.mean(errors[k]))
        if max(times[k]) > 3 * min(times[k]):
            print(f"warning: {k}: render times vary more than 3x: {times[k]}", flush=True)
        out[k] = {"spp": n[k], "median_s": t, "times_s": times[k], "rel_mse": e,
                  "rel_mse_runs": errors[k], "reference_floor": floor,
                  "rel_mse_raw": float(np.mean(raw[k])),
                  "efficiency": stats.efficiency(e, t), "s_per_spp": per_spp[k],
                  "nan_inf_samples": invalid[k]}
        if guided[k]:
            out[k]["guiding_runs"] = guided[k]
    base = out["builtin"]
    for k in variants:
        r = out[k]
        r["efficiency_ratio"] = r["efficiency"] / base["efficiency"]
        r["efficiency_ratio_raw"] = (base["rel_mse_raw"] * base["median_s"]) / \
            (r["rel_mse_raw"] * r["median_s"])
        lo, hi = bootstrap_ratio(r["rel_mse_runs"], base["rel_mse_runs"])
        scale = base["median_s"] / r["median_s"]
        r["efficiency_ratio_90"] = [lo * scale, hi * scale]
    return out


def profile(scene, spp: int) -> dict:
    res = scene.sensors()[0].film().size()
    with instrument.counting() as counts:
        mi.render(scene, integrator=integrator(VARIANTS["old_default"]), spp=spp, seed=99)
        out = {k: v / (spp * res[0] * res[1]) for k, v in counts.as_dict().items()}
    out["lookups"] = out["flight_null"] + out["shadow_tentative"]
    return out


def rel_variance(scene, variant: dict, spp: int, runs: int) -> float:
    """Relative variance per sample: mean over pixels of var / (mean^2 + eps), x spp."""
    integ = integrator(variant)
    return relative_variance([timed_render(scene, integ, spp, seed=1000 + r)[1]
                              for r in range(runs)], spp)


def relative_variance(images, spp: int) -> float:
    """Mean over pixels of var / (mean^2 + eps) over ``images`` of ``spp`` each, x spp."""
    a = np.array(images)
    return float(np.mean(a.var(0, ddof=1) / (a.mean(0) ** 2 + stats.REL_MSE_EPS)) * spp)


def variance_split(scene, case: Case, spp: int, runs: int) -> dict:
    base = VARIANTS["old_default"]
    out = {"all": rel_variance(scene, base, spp, runs)}
    for depth in (1, 2, 4, 8):
        out[f"depth<={depth}"] = rel_variance(scene, {**base, "max_depth": depth}, spp, runs)
    for terms in (("nee",), ("emission",)):
        with instrument.only_terms(*terms):
            out[f"{terms[0]} only"] = rel_variance(scene, base, spp, runs)
    if case.shape != "homogeneous":
        for m in ("ratio", "residual"):
            out[f"transmittance={m}"] = rel_variance(scene, {**base, "transmittance": m}, spp,
                                                     runs)
    return out


SWEEP = (1, 2, 4, 8, 16, 32)


def majorant_sweep(case: Case, res: int, spp: int, runs: int, tmp: Path) -> dict:
    """volpath_delta (defaults) with the majorant grid at each resolution of :data:`SWEEP`
    and the automatic choice: time per sample (median of ``runs`` alternating renders of
    ``spp``), relative variance per sample (over the same renders) and efficiency, each
    relative to volpath's."""
    configs = {"volpath": None, "auto": {"medium": {}},
               **{str(n): {"medium": {"majorant_resolution": n}} for n in SWEEP}}
    sc = scene(case, res, tmp)
    integ = {k: mi.load_dict(BUILTIN if v is None else VARIANTS["volpath_delta"])
             for k, v in configs.items()}
    for k in configs:
        render_variant(sc, integ[k], configs[k], spp, seed=10 ** 6)
    times, imgs = alternate(configs, runs, lambda k, run: render_variant(
        sc, integ[k], configs[k], spp, seed=1000 + run))
    t0, v0 = statistics.median(times["volpath"]), relative_variance(imgs["volpath"], spp)
    set_medium(sc, None)
    grid = next(sh for sh in sc.shapes() if sh.interior_medium() is not None)
    out = {"auto_resolution": list(grid.interior_medium().majorant_grid.resolution),
           "default_before": DEFAULT_RESOLUTION}
    for k in list(configs)[1:]:
        t, v = statistics.median(times[k]) / t0, relative_variance(imgs[k], spp) / v0
        out[k] = {"time": t, "variance": v, "efficiency": 1.0 / (t * v)}
    return out


def sweep_markdown(result: dict) -> str:
    cfg = result["config"]
    cols = ["auto"] + [str(n) for n in SWEEP]
    lines = [
        "# Majorant grid resolution on the dense family (volpath_delta against volpath)", "",
        f"Measured {result['date']} on {result['cpu']} ({VARIANT}, Mitsuba {mi.__version__}) by "
        f"`python3 -m benchmarks.dense {cfg['argv']}` (res {cfg['res']}, {cfg['spp']} spp, "
        f"{cfg['runs']} alternating renders of each: time = median time / volpath's, variance = "
        "relative variance per sample over the renders / volpath's, efficiency = 1 / (time x "
        "variance)). Columns: the automatic choice (`majorant.auto_resolution`, the default) "
        "and fixed cells per axis (16 was the default before).", "",
        "| scene | auto picks | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]
    for name, r in result["cases"].items():
        lines.append(f"| {name} | {r['auto_resolution'][0]} | " + " | ".join(
            f"**{r[c]['efficiency']:.2f}x** ({r[c]['time']:.2f} time, {r[c]['variance']:.2f} var)"
            for c in cols) + " |")
    return "\n".join(lines) + "\n"


# -- report -------------------------------------------------------------------------------------
def markdown(result: dict) -> str:
    cfg = result["config"]
    variants = cfg["variants"]
    lines = [
        "# Dense-media family: volpath_delta against Mitsuba's volpath", "",
        f"Measured {result['date']} on {result['cpu']} ({VARIANT}, Mitsuba {mi.__version__}) by "
        f"`python3 -m benchmarks.dense {cfg['argv']}` (res {cfg['res']}, volpath {cfg['spp']} "
        f"spp, {cfg['runs']} alternating runs at equal time, median time, mean relMSE; "
        "volpath s/spp and time/spp: measured time per sample, ours over volpath's for "
        f"the latter; reference {cfg['ref_spp']} spp of {cfg['reference']}; max_depth -1). The family and the "
        "method are in the script's docstring.", "",
        "## Efficiency against volpath at equal time (90% bootstrap interval over runs)", "",
        "| scene | max/mean | tau | albedo | g | light | volpath s/spp | "
        + " | ".join(f"{v}" for v in variants) + " |",
        "|---|---|---|---|---|---|---|" + "---|" * len(variants)]
    for name, r in result["cases"].items():
        c = r["case"]
        e = r["efficiency"]
        lines.append(
            f"| {name} | {c['max_over_mean']:g} | {c['tau']:g} | {c['albedo']:g} | {c['g']:g} | "
            f"{c['light']} | {e['builtin']['median_s'] / e['builtin']['spp']:.3f} | " + " | ".join(
                f"**{e[v]['efficiency_ratio']:.2f}x** ({e[v]['efficiency_ratio_90'][0]:.2f}-"
                f"{e[v]['efficiency_ratio_90'][1]:.2f}), {time_per_sample_ratio(e, v):.2f}"
                " time/spp" for v in variants) + " |")
    lines += ["", "| summary | " + " | ".join(variants) + " |", "|---|" + "---|" * len(variants)]
    for label, fn in (("median", statistics.median), ("min", min)):
        lines.append(f"| {label} | " + " | ".join(
            f"{fn(r['efficiency'][v]['efficiency_ratio'] for r in result['cases'].values()):.2f}x"
            for v in variants) + " |")
    if any("bias" in r for r in result["cases"].values()):
        biased = [k for k in next(r["bias"] for r in result["cases"].values() if "bias" in r)
                  if not k.startswith("noise_floor")]
        lines += ["", f"## Bias ({cfg['ref_spp']} spp of each against the reference: relative "
                  "error of the image total, and relMSE next to that of as many samples of the "
                  "unbiased reference integrator)", "",
                  "| scene | unbiased: total, relMSE | " + " | ".join(
                      f"{k}: total, relMSE" for k in biased) + " |",
                  "|---|---|" + "---|" * len(biased)]
        for name, r in result["cases"].items():
            if "bias" in r:
                b = r["bias"]
                lines.append(f"| {name} | {100 * b['noise_floor_energy']:+.2f}%, "
                             f"{b['noise_floor']:.2e} | " + " | ".join(
                                 f"{100 * b[k]['energy']:+.2f}%, {b[k]['rel_mse']:.2e}"
                                 for k in biased) + " |")
    if any("profile" in r for r in result["cases"].values()):
        slots = list(next(r["profile"] for r in result["cases"].values() if "profile" in r))
        lines += ["", "## Where the time goes (volpath_delta with the defaults before issue "
                  "16, per camera path)", "",
                  "| scene | " + " | ".join(slots) + " |", "|---|" + "---|" * len(slots)]
        for name, r in result["cases"].items():
            if "profile" in r:
                lines.append(f"| {name} | " + " | ".join(f"{r['profile'][s]:.2f}"
                                                          for s in slots) + " |")
    if any("variance" in r for r in result["cases"].values()):
        cols = ["all", "depth<=1", "depth<=2", "depth<=4", "depth<=8", "nee only",
                "emission only", "transmittance=ratio", "transmittance=residual"]
        lines += ["", "## Where the variance goes (volpath_delta, relative variance per "
                  "sample; defaults before issue 16: track_length, rr_max_survival 0.95)", "",
                  "| scene | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
        for name, r in result["cases"].items():
            if "variance" in r:
                v = r["variance"]
                lines.append(f"| {name} | " + " | ".join(
                    f"{v[c]:.3g}" if c in v else "-" for c in cols) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    import sys
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--runs", type=int, default=6)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--cases", default=",".join(c.name for c in FAMILY))
    ap.add_argument("--variants", default="volpath_delta")
    ap.add_argument("--no-profile", action="store_true", help="skip the time/variance profile")
    ap.add_argument("--bias", default="", help="variants whose bias to measure (ref-spp "
                    "samples each against the reference), comma-separated")
    ap.add_argument("--majorant-sweep", action="store_true",
                    help="time and variance per majorant resolution instead (heterogeneous cases)")
    ap.add_argument("--out", default=None, help="results path without suffix (default: "
                    "benchmarks/results/dense, or dense_majorant with --majorant-sweep)")
    args = ap.parse_args()
    out = Path(args.out or ROOT / "benchmarks" / "results" /
               ("dense_majorant" if args.majorant_sweep else "dense"))
    variants = {v: VARIANTS[v] for v in args.variants.split(",")}
    cases = [c for c in FAMILY if c.name in args.cases.split(",")]
    result = {"date": datetime.date.today().isoformat(), "cpu": device_model(VARIANT),
              "variant": VARIANT, "cases": {},
              "config": {"res": args.res, "spp": args.spp, "runs": args.runs,
                         "ref_spp": args.ref_spp, "reference": REFERENCE, "variants": list(variants),
                         "argv": " ".join(sys.argv[1:])}}
    if args.majorant_sweep:
        with tempfile.TemporaryDirectory() as tmpdir:
            for case in cases:
                if case.shape == "homogeneous":
                    continue
                result["cases"][case.name] = majorant_sweep(case, args.res, args.spp,
                                                            args.runs, Path(tmpdir))
                print(case.name, {k: round(v["efficiency"], 2) for k, v in
                                  result["cases"][case.name].items() if isinstance(v, dict)},
                      flush=True)
                output.write_json(out.with_suffix(".json"), result, indent=1)
                output.write_text(out.with_suffix(".md"), sweep_markdown(result))
        return
    with tempfile.TemporaryDirectory() as tmpdir:
        for case in cases:
            sc = scene(case, args.res, Path(tmpdir))
            ref = reference(sc, args.ref_spp)
            r = {"case": asdict(case),
                 "efficiency": equal_time(sc, variants, args.spp, args.runs, ref)}
            if args.bias:
                r["bias"] = bias(sc, {v: VARIANTS[v] for v in args.bias.split(",")},
                                 args.ref_spp, ref)
            if not args.no_profile:
                set_medium(sc, VARIANTS["old_default"]["medium"])
                r["profile"] = profile(sc, args.spp)
                r["variance"] = variance_split(sc, case, args.spp, max(4, args.runs))
            set_medium(sc, None)
            result["cases"][case.name] = r
            print(case.name, ", ".join(f"{v} {r['efficiency'][v]['efficiency_ratio']:.2f}x"
                                       for v in variants), flush=True)
            output.write_json(out.with_suffix(".json"), result, indent=1)
            output.write_text(out.with_suffix(".md"), markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
