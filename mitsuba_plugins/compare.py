"""Speed against error: render integrators on one scene and measure each against a
high-spp reference from the matching Mitsuba built-in (ALGORITHMS.md section 1)."""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mitsuba_plugins import stats

#: Our plugin -> the Mitsuba built-in that estimates the same quantity, and the
#: parameters of ours that the built-in understands (passed on to the reference).
BUILTIN = {"direct_mis": "direct", "path_rr": "path", "volpath_delta": "volpath",
           "volpath_raymarch": "volpath"}
BUILTIN_PARAMS = {
    "direct": ("shading_samples", "emitter_samples", "bsdf_samples", "hide_emitters"),
    "path": ("max_depth", "rr_depth", "hide_emitters"),
    "volpath": ("max_depth", "rr_depth", "hide_emitters"),
}
REFERENCE_PASSES = 16


def parse_integrator(spec: str) -> dict:
    """``name`` or ``name:key=value:key=value`` -> a Mitsuba plugin dict."""
    name, *pairs = spec.strip().split(":")
    if not name:
        raise ValueError(f"empty integrator name in '{spec}'")
    out = {"type": name}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise ValueError(f"integrator option '{pair}' in '{spec}' is not of the form key=value")
        out[key] = _parse_value(value)
    return out


def _parse_value(text: str):
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def label(integrator: dict) -> str:
    extra = ":".join(f"{k}={v}" for k, v in integrator.items() if k != "type")
    return integrator["type"] + (":" + extra if extra else "")


def reference_for(integrator: dict) -> dict:
    """The built-in integrator (with the parameters it shares) that serves as reference."""
    name = integrator["type"]
    builtin = BUILTIN.get(name, name)
    if builtin not in BUILTIN_PARAMS:
        raise ValueError(f"no reference known for integrator '{name}'; known: "
                         f"{', '.join(sorted(set(BUILTIN) | set(BUILTIN_PARAMS)))}")
    return {"type": builtin, **{k: v for k, v in integrator.items() if k in BUILTIN_PARAMS[builtin]}}


def load_scene(path: str, res: int | None = None):
    import mitsuba as mi
    if not Path(path).is_file():
        raise FileNotFoundError(f"scene file not found: {path}")
    params = {"res": str(res)} if res else {}
    return mi.load_file(str(path), **params)


def cached_reference(scene, scene_path: str, res, reference: dict, spp: int, cache_dir: Path,
                     seed: int = 0x5EED0000, progress: bool = True) -> stats.Estimate:
    """High-spp reference, cached on disk keyed by scene file content, resolution,
    integrator, spp and variant."""
    import mitsuba as mi
    key = hashlib.sha256(json.dumps({
        "scene": hashlib.sha256(Path(scene_path).read_bytes()).hexdigest(), "res": res,
        "integrator": reference, "spp": spp, "variant": mi.variant(), "seed": seed,
    }, sort_keys=True).encode()).hexdigest()[:20]
    path = cache_dir / f"{Path(scene_path).stem}-{reference['type']}-{spp}spp-{key}.npz"
    if path.exists():
        data = np.load(path)
        return stats.Estimate(data["mean"], data["se"], int(data["passes"]), int(data["spp_per_pass"]))
    per_pass = max(1, spp // REFERENCE_PASSES)
    est = stats.render_passes(scene, REFERENCE_PASSES, per_pass, integrator=mi.load_dict(reference),
                              seed=seed, warmup=False,
                              progress=f"reference {label(reference)} {spp} spp" if progress else None)
    if est.invalid:
        raise RuntimeError(f"reference {label(reference)} produced {est.invalid} NaN/Inf values")
    cache_dir.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, mean=est.mean, se=est.se, passes=est.passes, spp_per_pass=est.spp_per_pass)
    return est


@dataclass
class Row:
    integrator: str
    reference: str
    spp: int
    seconds: float
    rel_mse: float
    efficiency: float
    invalid: int
    time_ratio: float = math.nan         # seconds / built-in's seconds (same reference)
    efficiency_ratio: float = math.nan   # efficiency / built-in's efficiency
    image: np.ndarray | None = None


def compare(scene_path: str, integrators: list[dict], spp: int, passes: int = 4,
            ref_spp: int | None = None, res: int | None = None, cache_dir: Path = Path(".cache/references"),
            seed: int = 0, progress: bool = True) -> list[Row]:
    import mitsuba as mi
    if spp < passes:
        raise ValueError(f"--spp ({spp}) must be >= --passes ({passes})")
    scene = load_scene(scene_path, res)
    ref_spp = ref_spp or max(1024, 16 * spp)
    rows, references = [], {}
    for integrator in integrators:
        integ = mi.load_dict(integrator)  # validates parameters before any rendering
        reference = reference_for(integrator)
        ref_label = label(reference)
        if ref_label not in references:
            references[ref_label] = cached_reference(scene, scene_path, res, reference, ref_spp,
                                                     Path(cache_dir), progress=progress)
        ref = references[ref_label]
        est = stats.render_passes(scene, passes, max(1, spp // passes), integrator=integ, seed=seed,
                                  progress=label(integrator) if progress else None)
        err = stats.rel_mse(est.mean, ref.mean)
        rows.append(Row(label(integrator), f"{ref_label} @ {ref.spp} spp", est.spp, est.seconds, err,
                        stats.efficiency(err, est.seconds), est.invalid, image=est.mean))
    for row, integrator in zip(rows, integrators):
        builtin = next((r for r, i in zip(rows, integrators)
                        if i == reference_for(integrator) and r is not row), None)
        if builtin is not None:
            row.time_ratio = row.seconds / builtin.seconds
            row.efficiency_ratio = row.efficiency / builtin.efficiency
    return rows


def format_table(rows: list[Row]) -> str:
    head = ("integrator", "reference", "spp", "time [s]", "rel. MSE", "efficiency",
            "time / built-in", "eff. / built-in", "NaN/Inf")
    body = [(r.integrator, r.reference, str(r.spp), f"{r.seconds:.3f}", f"{r.rel_mse:.3e}",
             f"{r.efficiency:.4g}", _ratio(r.time_ratio), _ratio(r.efficiency_ratio), str(r.invalid))
            for r in rows]
    widths = [max(len(x) for x in col) for col in zip(head, *body)]
    line = lambda cells: "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"  # noqa: E731
    return "\n".join([line(head), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + [line(b) for b in body])


def _ratio(x: float) -> str:
    return "-" if math.isnan(x) else f"{x:.3f}"
