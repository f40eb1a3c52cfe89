"""Speed against error: render integrators on one scene and measure each against a
high-spp reference from the matching Mitsuba built-in (docs/method.md section 1).

Two modes. Equal spp: every integrator renders ``passes`` passes of ``spp / passes``
samples. Equal time: every integrator renders passes of ``spp_per_pass`` samples until
its ``time_budget`` is spent. In both, the integrators take turns pass by pass (so a slow
drift of the machine affects all alike), every pass is timed after a warm-up render that
compiles the kernel, and the running estimate's relative MSE is recorded after each pass:
the error-against-time curve.
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mitsuba_plugins import output
from mitsuba_plugins.tools import metrics, stats
from mitsuba_plugins.tools.integrator_specs import (builtin_twin, check_reference, ignores,
                                                    is_ours, label, reference_for)
from mitsuba_plugins.tools.scenes import load_scene, scene_digest

REFERENCE_PASSES = 16


#: a reference limits a measurement when its own rel. MSE exceeds this share of the
#: measured (uncorrected) one
FLOOR_SHARE = 0.25


#: what a reference-cache entry holds (``.npz``); ``checksum`` covers all the others
CACHE_FIELDS = ("mean", "se", "passes", "spp_per_pass", "meta")
CACHE_FORMAT = 2


def _cache_checksum(fields: dict) -> str:
    digest = hashlib.sha256()
    for name in CACHE_FIELDS:
        value = np.asarray(fields[name])
        digest.update(name.encode() + str(value.dtype).encode() + str(value.shape).encode())
        digest.update(np.ascontiguousarray(value).tobytes())
    return digest.hexdigest()


def _read_cache_entry(path: Path, meta: str, size: tuple):
    """``(estimate, None)`` from the entry at ``path``, or ``(None, reason)`` when it is
    unreadable, misses fields, does not match its checksum, was made with other
    settings, is not an image of ``size = (height, width)`` or holds non-finite values."""
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in CACHE_FIELDS + ("checksum",) if k not in data.files]
            if missing:
                return None, f"missing field(s) {', '.join(missing)}"
            fields = {k: data[k] for k in CACHE_FIELDS}
            checksum = str(data["checksum"])
    except Exception as error:  # zip, zlib, numpy format errors: all mean 'damaged'
        return None, f"unreadable ({type(error).__name__}: {error})"
    if _cache_checksum(fields) != checksum:
        return None, "content does not match its checksum"
    if str(fields["meta"]) != meta:
        return None, "made with other settings"
    mean, se = fields["mean"], fields["se"]
    if mean.ndim != 3 or mean.shape[:2] != tuple(size) or se.shape != mean.shape:
        return None, f"image shape {mean.shape}, expected {tuple(size)} x channels"
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(se)) and np.all(se >= 0)):
        return None, "non-finite values"
    return stats.Estimate(mean, se, int(fields["passes"]), int(fields["spp_per_pass"])), None


def _write_cache_entry(path: Path, est: stats.Estimate, meta: str) -> None:
    fields = {"mean": np.asarray(est.mean, np.float64), "se": np.asarray(est.se, np.float64),
              "passes": np.int64(est.passes), "spp_per_pass": np.int64(est.spp_per_pass),
              "meta": np.str_(meta)}
    buffer = io.BytesIO()
    np.savez_compressed(buffer, checksum=np.str_(_cache_checksum(fields)), **fields)
    with output.atomic_path(path) as tmp:
        Path(tmp).write_bytes(buffer.getvalue())
    for suffix, image in (("", est.mean), ("_se", est.se)):
        output.write_exr(path.with_name(path.stem + suffix + ".exr"), image)


def cached_reference(scene, scene_path: str, res, reference: dict, spp: int, cache_dir: Path,
                     seed: int = 0x5EED0000, progress: bool = True,
                     scheduler: str | None = None) -> stats.Estimate:
    """High-spp reference (mean of 16 passes and its per-pixel standard error), cached on
    disk keyed by scene content (:func:`scene_digest`), resolution, integrator, spp and
    variant. Next to the ``.npz`` the mean and standard-error images are written as EXR.

    Each entry stores these settings and a SHA-256 of its content; an entry that fails
    any check on reading (:func:`_read_cache_entry`) is rebuilt, with a line on stderr
    naming the file and what was wrong with it."""
    import mitsuba as mi
    meta = json.dumps({
        "format": CACHE_FORMAT, "scene": scene_digest(scene_path), "res": res,
        "integrator": reference, "spp": spp, "variant": mi.variant(), "seed": seed,
    }, sort_keys=True)
    key = hashlib.sha256(meta.encode()).hexdigest()[:20]
    path = Path(cache_dir) / f"{Path(scene_path).stem}-{reference['type']}-{spp}spp-{key}.npz"
    per_pass = max(1, spp // REFERENCE_PASSES)
    if path.exists():
        width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
        est, reason = _read_cache_entry(path, meta, (height, width))
        if est is not None:
            return est
        print(f"mitsuba-plugins: reference cache entry '{path}' is damaged ({reason}); "
              "rebuilding it", file=sys.stderr)
    if scheduler:   # the same passes and seeds, as tasks on a Dask cluster
        from mitsuba_plugins.tools.reference import estimate_on_cluster
        est = estimate_on_cluster(scene_path, res, reference, per_pass, REFERENCE_PASSES, seed,
                                  scheduler=scheduler, progress=progress)
    else:
        est = stats.render_passes(scene, REFERENCE_PASSES, per_pass, integrator=mi.load_dict(reference),
                                  seed=seed, warmup=False,
                                  progress=f"reference {label(reference)} {spp} spp"
                                  if progress else None)
    if est.invalid:
        raise RuntimeError(f"reference {label(reference)} produced {est.invalid} NaN/Inf samples")
    _write_cache_entry(path, est, meta)
    return est


def reference_floor(ref: stats.Estimate) -> float:
    """The reference's own relative MSE, mean(se^2 / (ref^2 + eps)).

    An image ``x`` independent of the reference ``r`` has E[(x - r)^2] = MSE(x) + Var(r),
    so this (unbiased, from the reference's passes) is subtracted from every measured
    rel. MSE: a finite reference then does not flatten the ratios between integrators."""
    return float(np.mean(ref.se ** 2 / (ref.mean ** 2 + stats.REL_MSE_EPS)))


@dataclass
class Row:
    """One integrator's measurement. ``seconds`` is the sum of its timed passes."""
    integrator: str
    reference: str                       # label of the reference integrator
    reference_spp: int
    spp: int
    passes: int
    seconds: float
    rel_mse: float                       # measured minus the reference's own (reference_floor)
    rel_mse_measured: float              # against the reference, uncorrected
    efficiency: float                    # 1 / (rel. MSE x seconds)
    invalid: int                         # NaN/Inf samples (counted in the kernel)
    builtin: bool                        # a Mitsuba built-in (not one of our plugins)
    ignores: str = ""                    # the part of the scene it does not render (ignores)
    rel_mse_trimmed: float = math.nan    # the other metrics of tools.metrics, beside rel. MSE
    mape: float = math.nan
    smape: float = math.nan
    flip: float = math.nan
    ttuv: float = math.nan               # time to unit variance: rel. MSE x seconds
    time_ratio: float = math.nan         # seconds / its built-in counterpart's seconds
    rel_mse_ratio: float = math.nan      # rel. MSE / built-in's
    efficiency_ratio: float = math.nan   # efficiency / built-in's efficiency
    curve_seconds: list = field(default_factory=list)   # cumulative time after each pass
    curve_rel_mse: list = field(default_factory=list)   # rel. MSE of the running mean (corrected)
    curve_rel_mse_trimmed: list = field(default_factory=list)   # and its other metrics
    curve_mape: list = field(default_factory=list)
    curve_smape: list = field(default_factory=list)
    curve_flip: list = field(default_factory=list)
    image: np.ndarray | None = None

    def curve(self, metric: str) -> list:
        """The running estimate's value of ``metric`` (one of ``metrics.NAMES``) after each pass."""
        return getattr(self, "curve_" + metric)

    def to_dict(self) -> dict:
        out = {k: v for k, v in self.__dict__.items() if k != "image"}
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in out.items()}


@dataclass
class Report:
    """Outcome of :func:`compare`: rows, references (by label) and how they were made."""
    scene: str
    mode: str                            # "equal-spp" or "equal-time"
    rows: list
    references: dict                     # label -> stats.Estimate
    time_budget: float | None = None
    spp_per_pass: int = 0

    def floors(self) -> dict:
        return {k: reference_floor(v) for k, v in self.references.items()}

    def to_dict(self) -> dict:
        floors = self.floors()
        return {"scene": self.scene, "mode": self.mode, "time_budget": self.time_budget,
                "spp_per_pass": self.spp_per_pass,
                "references": {k: {"spp": v.spp, "passes": v.passes, "rel_mse_floor": floors[k]}
                               for k, v in self.references.items()},
                "rel_mse_definition": f"mean((x - ref)^2 / (ref^2 + {stats.REL_MSE_EPS})) minus "
                                      "the reference's own (rel_mse_floor)",
                "rows": [r.to_dict() for r in self.rows]}


class _Run:
    """One integrator being measured: running sum, timed passes, curve."""

    def __init__(self, spec: dict, scene, reference: dict | None = None):
        import mitsuba as mi
        from mitsuba_plugins.validity import counted
        self.spec = spec
        self.ignores = ignores(scene, spec["type"])
        self.reference_spec = reference or reference_for(spec, scene)
        self.reference = label(self.reference_spec)
        self.ref: stats.Estimate | None = None          # set with the reference (use_reference)
        self.floor, self.measured = 0.0, math.nan
        self.integrator = counted(mi.load_dict(spec))   # validates parameters first
        self.total, self.passes, self.seconds, self.invalid = None, 0, 0.0, 0
        self.curve_seconds, self.curves = [], {name: [] for name in metrics.NAMES}

    def use_reference(self, ref: stats.Estimate):
        self.ref, self.floor = ref, reference_floor(ref)

    def warm_up(self, scene, spp: int):
        """Compile; neither the time nor the count is kept."""
        stats.timed_pass(scene, self.integrator, spp, stats.WARMUP_SEED)

    def step(self, scene, spp: int, seed: int):
        seconds, arr, invalid = stats.timed_pass(scene, self.integrator, spp, seed)
        self.seconds += seconds
        self.invalid += invalid
        self.total = arr if self.total is None else self.total + arr
        self.passes += 1
        self.curve_seconds.append(self.seconds)
        self.measured = stats.rel_mse(self.total / self.passes, self.ref.mean)
        for name, value in metrics.measure(self.total / self.passes, self.ref, self.floor).items():
            self.curves[name].append(value)

    def row(self, spp_per_pass: int) -> Row:
        last = {name: values[-1] for name, values in self.curves.items()}
        err = last["rel_mse"]
        return Row(label(self.spec), self.reference, self.ref.spp, self.passes * spp_per_pass,
                   self.passes, self.seconds, err, self.measured,
                   stats.efficiency(err, self.seconds),
                   self.invalid, not is_ours(self.spec["type"]), ignores=self.ignores,
                   **{k: v for k, v in last.items() if k != "rel_mse"},
                   ttuv=metrics.time_to_unit_variance(err, self.seconds),
                   curve_seconds=list(self.curve_seconds),
                   **{"curve_" + k: list(v) for k, v in self.curves.items()},
                   image=self.total / self.passes)


def compare(scene_path: str, integrators: list[dict], spp: int = 64, passes: int = 4,
            time_budget: float | None = None, spp_per_pass: int | None = None,
            ref_spp: int | None = None, res: int | None = None,
            cache_dir: Path = Path(".cache/references"), seed: int = 0,
            progress: bool = True, reference: dict | None = None,
            scheduler: str | None = None) -> Report:
    """Measure ``integrators`` on one scene, at equal spp (``spp`` in ``passes``) or, with
    ``time_budget`` seconds, at equal time (passes of ``spp_per_pass``, default 16).

    Each is measured against the built-in that estimates the same quantity
    (:func:`reference_for`), or against ``reference`` for all (e.g. where the built-in
    is biased); ratios are to the built-in row, whichever the reference. ``scheduler``:
    render missing references as tasks on that Dask cluster (the timed rows always run
    here, in this process: times are never summed across machines)."""
    if spp_per_pass is not None and spp_per_pass < 1:
        raise ValueError(f"--spp-per-pass must be >= 1; got {spp_per_pass}")
    if ref_spp is not None and ref_spp < REFERENCE_PASSES:
        raise ValueError(f"--ref-spp must be >= {REFERENCE_PASSES} (one per reference pass); "
                         f"got {ref_spp}")
    if time_budget is not None:
        if not (math.isfinite(time_budget) and time_budget > 0):
            raise ValueError(f"--time-budget = {time_budget} is invalid; allowed: a finite "
                             "number of seconds > 0")
        spp_per_pass = spp_per_pass or 16
        ref_spp = ref_spp or 4096
    else:
        if passes < 1 or spp < passes:
            raise ValueError(f"--spp ({spp}) must be >= --passes ({passes}) >= 1")
        if spp_per_pass is None and spp % passes:
            raise ValueError(f"--spp = {spp} is invalid; allowed: a multiple of --passes "
                             f"({passes}), which split it into equal passes")
        spp_per_pass = spp_per_pass or spp // passes
        ref_spp = ref_spp or max(1024, 16 * spp)
    if not integrators:
        raise ValueError("no integrators given")
    labels = [label(spec) for spec in integrators]
    twice = sorted({name for name in labels if labels.count(name) > 1})
    if twice:
        raise ValueError(f"-i lists {', '.join(repr(n) for n in twice)} more than once; "
                         "allowed: each integrator (with its parameters) once")
    scene = load_scene(scene_path, res)
    if reference is not None:
        check_reference(reference, scene, scene_path)
    references = {}
    runs = [_Run(spec, scene, reference) for spec in integrators]   # validated before rendering
    for run in runs:
        if run.reference not in references:
            references[run.reference] = cached_reference(scene, scene_path, res, run.reference_spec,
                                                         ref_spp, Path(cache_dir), progress=progress,
                                                         scheduler=scheduler)
        run.use_reference(references[run.reference])
    for name, ref in references.items():
        if not np.any(ref.mean):
            why = "the scene has no emitter" if not scene.emitters() else \
                "no light reaches the sensor"
            raise ValueError(f"the reference image ({name}) is black: {why}, so relative MSE "
                             "and efficiency are undefined")
    for run in runs:
        run.warm_up(scene, spp_per_pass)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=time_budget * len(runs) if time_budget else passes * len(runs),
                   desc="equal time" if time_budget else "equal spp", leave=False,
                   unit="s" if time_budget else "pass",
                   bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} {unit}")
    k = 0
    while True:
        todo = [r for r in runs if (r.seconds < time_budget if time_budget else r.passes < passes)]
        if not todo:
            break
        for run in todo:                  # take turns, pass by pass
            before = run.seconds
            run.step(scene, spp_per_pass, (seed + k) % 2 ** 32)  # Mitsuba seeds are uint32
            if bar is not None:
                bar.update(min(run.seconds, time_budget) - min(before, time_budget)
                           if time_budget else 1)
        k += 1
    if bar is not None:
        bar.close()
    rows = [run.row(spp_per_pass) for run in runs]
    for row, spec in zip(rows, integrators):
        twin = builtin_twin(spec)
        builtin = next((r for r, s in zip(rows, integrators) if s == twin and r is not row), None)
        # a built-in that leaves part of the scene out renders another image: no ratio
        if builtin is not None and not builtin.ignores:
            row.time_ratio = row.seconds / builtin.seconds
            row.rel_mse_ratio = row.rel_mse / builtin.rel_mse if builtin.rel_mse > 0 else math.nan
            row.efficiency_ratio = row.efficiency / builtin.efficiency
    return Report(str(scene_path), "equal-time" if time_budget else "equal-spp", rows, references,
                  time_budget, spp_per_pass)
