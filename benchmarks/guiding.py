"""Does path guiding pay inside one ordinary render, training included? (issue 47)

Each scene: a reference (``benchmarks.dense.REFERENCE`` at ``--ref-spp``), then
:func:`benchmarks.dense.equal_time`: Mitsuba's ``volpath`` at ``--spp`` and each
configuration of ``volpath_delta`` at the sample count that takes as long (its training
passes inside that render: a guided render is one ``mi.render`` call), ``--runs``
alternating renders each; efficiency = 1 / (mean relMSE x median time), its ratio to
``volpath``'s and the relative MSE per sample. The scenes are split: the tuning set chose
the defaults (``guiding_candidates``, ``guiding_resolution``, ``guiding_training``), the
test set reports them.

* tuning: a dense gray ball under a small light (sigma_t 20, albedo 0.95, HG 0.5), a fog
  room lit through a hole in one wall (camera inside the fog), a fog ball holding a small
  lamp, a cube of forward-scattering fog (HG 0.75) holding a small lamp, a cube of
  forward-scattering fog (HG 0.85) under a small light outside it;
* test: the smooth smoke of scenes/smoke.xml under its area light, a camera inside a
  forward-scattering cloud (HG 0.6), a strongly forward-scattering ball (HG 0.9), a dense
  chromatic ball under an environment;
* cost (``--set cost``, not in ``both``): where guiding cannot pay, what it costs: thin
  fog balls (sigma_t 0.2 and 0.02) under the small light and an environment.

``python3 -m benchmarks.guiding [--set tuning|test|both] [--configs a,b]`` writes
``benchmarks/results/guiding.{md,json}``; ``--surfaces --spp 256 --out
benchmarks/results/guiding_surfaces``: ``path_rr`` with and without ``guiding =
surfaces`` against ``path`` (tuning: a room lit only by light bounced outside through a
hole; test: a room lit the same way through a door, a room lit through a slit, the Cornell
box); ``--picture`` draws the field learnt in the
dense ball, ``docs/results/guiding_field.png``; ``--ceiling --out
benchmarks/results/guiding_ceiling``: what directional guiding could give with a field
learnt long beforehand (a 2048-spp training render, then frozen), at equal sample count;
``--ceiling --surfaces --set tuning --train 1024 --out
benchmarks/results/guiding_surfaces_ceiling``: the same for ``path_rr``'s histograms.
"""
from __future__ import annotations

import argparse
import datetime
import sys
from pathlib import Path

from benchmarks import dense  # sets the variant
from benchmarks.harness import device_model
import mitsuba as mi

from mitsuba_plugins import output
from mitsuba_plugins.tools import stats
from mitsuba_plugins.tools.scenes import camera, homogeneous, media_scene

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = {
    "off": {"type": "volpath_delta"},
    "guided": {"type": "volpath_delta", "guiding": "volumes"},
    "guided_c8": {"type": "volpath_delta", "guiding": "volumes", "guiding_candidates": 8},
    "guided_r8": {"type": "volpath_delta", "guiding": "volumes", "guiding_resolution": 8},
    **{f"guided_t{round(100 * t)}": {"type": "volpath_delta", "guiding": "volumes",
                                     "guiding_training": t} for t in (0.125, 0.5)},
    # roulette by the learnt radiance (guiding_roulette; 0: directions only, as before)
    **{f"guided_rr{v:g}": {"type": "volpath_delta", "guiding": "volumes", "guiding_roulette": v}
       for v in (0.0, 0.1, 0.3, 1.0)},
    # guided distance sampling for next-event estimation (guiding_distance)
    **{f"guided_l{n}": {"type": "volpath_delta", "guiding": "volumes", "guiding_lobe": n}
       for n in (0, 1, 2, 3, 4)},
    **{f"guided_l{n}_c{c}": {"type": "volpath_delta", "guiding": "volumes", "guiding_lobe": n,
                             "guiding_candidates": c} for n in (1, 2, 4) for c in (2, 3)},
    "guided_nod": {"type": "volpath_delta", "guiding": "volumes", "guiding_distance": False},
    "guided_d_only": {"type": "volpath_delta", "guiding": "volumes", "guiding_roulette": 0.0,
                      "guiding_candidates": 1},
    **{f"guided_c{c}": {"type": "volpath_delta", "guiding": "volumes", "guiding_candidates": c}
       for c in (1, 2, 3)},
    # surfaces (path_rr), against Mitsuba's path
    "path_rr": {"type": "path_rr", "max_depth": 12},
    "path_rr_guided": {"type": "path_rr", "max_depth": 12, "guiding": "surfaces"},
    **{f"path_rr_guided_portal{a:g}": {"type": "path_rr", "max_depth": 12, "guiding": "surfaces",
                                       "guiding_portal": a} for a in (0, 0.05, 0.1, 0.2, 0.3)},
    "path_rr_guided_nonee": {"type": "path_rr", "max_depth": 12, "guiding": "surfaces",
                             "guiding_nee": False},
    "path_rr_guided_vmf": {"type": "path_rr", "max_depth": 12, "guiding": "surfaces",
                           "guiding_bins": 0},
    **{f"path_rr_guided_b{b}": {"type": "path_rr", "max_depth": 12, "guiding": "surfaces",
                                "guiding_bins": b} for b in (8, 32)},
    **{f"path_rr_guided_f{f:g}": {"type": "path_rr", "max_depth": 12, "guiding": "surfaces",
                                  "guiding_fraction": f} for f in (0.2, 0.3, 0.5, 0.7, 0.9)},
    **{f"path_rr_guided_b{b}_f{f:g}": {"type": "path_rr", "max_depth": 12, "guiding": "surfaces",
                                       "guiding_bins": b, "guiding_fraction": f}
       for b in (0, 8, 16) for f in (0.2, 0.3, 0.5)},
    **{f"path_rr_guided_t{round(100 * t)}": {"type": "path_rr", "max_depth": 12,
                                             "guiding": "surfaces", "guiding_training": t}
       for t in (0.0625, 0.125, 0.5)},
    **{f"path_rr_guided_r16_f{f:g}": {"type": "path_rr", "max_depth": 12, "guiding": "surfaces",
                                      "guiding_resolution": 16, "guiding_fraction": f}
       for f in (0.2, 0.3, 0.5)},
    **{f"path_rr_guided_r{r}": {"type": "path_rr", "max_depth": 12, "guiding": "surfaces",
                                "guiding_resolution": r} for r in (6, 12)},
}


def _rect(center, axis: str, sign: int, size, bsdf=None, emitter=None) -> dict:
    T = mi.ScalarTransform4f
    t = T().translate(center)
    if axis == "x":
        t = t @ T().rotate([0, 1, 0], 90 * sign)
    elif axis == "y":
        t = t @ T().rotate([1, 0, 0], -90 * sign)
    elif sign < 0:
        t = t @ T().rotate([0, 1, 0], 180)
    d = {"type": "rectangle", "to_world": t @ T().scale([size[0] / 2, size[1] / 2, 1])}
    if bsdf:
        d["bsdf"] = bsdf
    if emitter:
        d["emitter"] = emitter
    return d


def _room_with_hole(h: float, white: dict) -> dict:
    """The walls of a closed 2 x 2 x 2 room with a square hole of side ``2 h`` in the middle
    of its wall at x = 1."""
    return {
        "floor": _rect([0, -1, 0], "y", 1, (2, 2), white),
        "ceiling": _rect([0, 1, 0], "y", -1, (2, 2), white),
        "back": _rect([-1, 0, 0], "x", 1, (2, 2), white),
        "left": _rect([0, 0, -1], "z", 1, (2, 2), white),
        "right": _rect([0, 0, 1], "z", -1, (2, 2), white),
        "wall_top": _rect([1, (1 + h) / 2, 0], "x", -1, (2, 1 - h), white),
        "wall_bottom": _rect([1, -(1 + h) / 2, 0], "x", -1, (2, 1 - h), white),
        "wall_left": _rect([1, 0, -(1 + h) / 2], "x", -1, (1 - h, 2 * h), white),
        "wall_right": _rect([1, 0, (1 + h) / 2], "x", -1, (1 - h, 2 * h), white),
    }


def gap_room(res: int) -> mi.Scene:
    """A closed room of white walls filled with fog (sigma_t 0.5, albedo 0.9), lit only
    through a 0.4-wide hole in one wall by an area light outside; the camera in the fog."""
    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}
    fog = {"type": "homogeneous", "sigma_t": 0.5, "albedo": 0.9}
    h = 0.2
    sensor = camera(res, origin=(-0.8, 0.0, 0.0), target=(1.0, 0.0, 0.0), fov=70.0, medium=fog)
    return mi.load_dict({
        "type": "scene", "sensor": sensor,
        "fog": {"type": "cube", "to_world": mi.ScalarTransform4f().scale(0.98),
                "bsdf": {"type": "null"}, "interior": fog},
        **_room_with_hole(h, white),
        "light": _rect([1.6, 0, 0], "x", -1, (0.8, 0.8),
                       emitter={"type": "area", "radiance": {"type": "rgb", "value": 40.0}}),
    })


def slit_room(res: int) -> mi.Scene:
    """A closed white room lit only through a 0.1-high slit at the top of one wall, by an
    area light outside above it (surfaces only: ``path_rr``'s guiding)."""
    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}
    h = 0.1
    return mi.load_dict({
        "type": "scene",
        "sensor": camera(res, origin=(-0.8, 0.0, 0.0), target=(1.0, 0.0, 0.0), fov=70.0),
        "floor": _rect([0, -1, 0], "y", 1, (2, 2), white),
        "ceiling": _rect([0, 1, 0], "y", -1, (2, 2), white),
        "back": _rect([-1, 0, 0], "x", 1, (2, 2), white),
        "left": _rect([0, 0, -1], "z", 1, (2, 2), white),
        "right": _rect([0, 0, 1], "z", -1, (2, 2), white),
        "wall": _rect([1, -h / 2, 0], "x", -1, (2, 2 - h), white),
        "outside_floor": _rect([1.5, -1, 0], "y", 1, (1.0, 2.0), white),
        "light": _rect([1.5, 1.3, 0], "y", -1, (1.0, 2.0),
                       emitter={"type": "area", "radiance": {"type": "rgb", "value": 20.0}}),
    })


def bounce_room(res: int) -> mi.Scene:
    """A closed white room with a 0.4 x 0.4 hole in one wall; outside it a light faces
    away from the room onto a white wall: every path that brings light in passes the
    hole and bounces once outside (surfaces, tuning set)."""
    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}
    h = 0.2
    return mi.load_dict({
        "type": "scene",
        "sensor": camera(res, origin=(-0.8, 0.0, 0.0), target=(1.0, 0.0, 0.0), fov=70.0),
        **_room_with_hole(h, white),
        "outside": _rect([2.4, 0, 0], "x", -1, (3, 3), white),
        "light": _rect([1.6, 0, 0], "x", 1, (0.6, 0.6),
                       emitter={"type": "area", "radiance": {"type": "rgb", "value": 400.0}}),
    })


def door_room(res: int) -> mi.Scene:
    """A closed white room with a door (0.4 wide, 1.2 high, from the floor) in one side
    wall; outside, a light on the floor faces up at a white ceiling, off to the door's
    side, so no point of the room sees it; the camera looks away from the door
    (surfaces, test set)."""
    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}
    return mi.load_dict({
        "type": "scene",
        "sensor": camera(res, origin=(0.8, 0.2, 0.6), target=(-1.0, -0.3, -0.4), fov=70.0),
        "floor": _rect([0, -1, 0], "y", 1, (2, 2), white),
        "ceiling": _rect([0, 1, 0], "y", -1, (2, 2), white),
        "back": _rect([-1, 0, 0], "x", 1, (2, 2), white),
        "front": _rect([1, 0, 0], "x", -1, (2, 2), white),
        "left": _rect([0, 0, -1], "z", 1, (2, 2), white),
        "right_a": _rect([-0.6, 0, 1], "z", -1, (0.8, 2), white),
        "right_b": _rect([0.6, 0, 1], "z", -1, (0.8, 2), white),
        "right_c": _rect([0, 0.6, 1], "z", -1, (0.4, 0.8), white),
        "out_floor": _rect([0, -1, 1.8], "y", 1, (4, 1.6), white),
        "out_ceiling": _rect([0, 1, 1.8], "y", -1, (4, 1.6), white),
        "out_wall": _rect([0, 0, 2.6], "z", -1, (4, 2), white),
        "light": _rect([1.2, -0.99, 1.8], "y", 1, (0.5, 0.5),
                       emitter={"type": "area", "radiance": {"type": "rgb", "value": 40.0}}),
    })


def _inside(res: int) -> mi.Scene:
    fog = homogeneous(0.6, albedo=0.9, g=0.6)
    return media_scene(extra={"fog": {"type": "sphere", "radius": 6.0, "bsdf": {"type": "null"},
                                      "interior": fog}},
                       sensor=camera(res, medium=fog), env=0)


def lamp_ball(res: int) -> mi.Scene:
    """A fog ball (sigma_t 1.5, albedo 0.8, isotropic) holding a small spherical lamp
    off its centre, over the floor; the camera outside (tuning: a light inside a medium)."""
    scene = media_scene(homogeneous(1.5, albedo=0.8), sensor=camera(res), env=0, as_dict=True)
    scene["light"] = {"type": "sphere", "center": [0.3, 0.2, -0.2], "radius": 0.08,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 400.0}}}
    return mi.load_dict(scene)


def forward_lamp(res: int) -> mi.Scene:
    """A fog cube of forward-scattering fog (sigma_t 1, albedo 0.9, HG g 0.75) holding a
    small spherical lamp, the camera outside (tuning: a light inside a medium whose phase
    function sends phase-sampled rays onto it)."""
    scene = media_scene(sensor=camera(res), env=0, as_dict=True, extra={
        "fog": {"type": "cube", "bsdf": {"type": "null"},
                "interior": homogeneous(1.0, albedo=0.9, g=0.75)}})
    scene["light"] = {"type": "sphere", "center": [-0.3, -0.2, 0.3], "radius": 0.08,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 400.0}}}
    return mi.load_dict(scene)


def forward_outside(res: int) -> mi.Scene:
    """A cube of forward-scattering fog (sigma_t 2, albedo 0.9, HG g 0.85) under the
    small light of ``media_scene`` outside it, the camera outside (tuning: a light outside
    a forward-scattering medium, for the phase-weighted distances toward it)."""
    scene = media_scene(sensor=camera(res), env=0, as_dict=True, extra={
        "fog": {"type": "cube", "bsdf": {"type": "null"},
                "interior": homogeneous(2.0, albedo=0.9, g=0.85)}})
    return mi.load_dict(scene)


SCENES = {
    "dense_ball": ("tuning", lambda res: media_scene(homogeneous(20.0, albedo=0.95, g=0.5),
                                                     sensor=camera(res), env=0)),
    "gap_room": ("tuning", gap_room),
    "lamp_ball": ("tuning", lamp_ball),
    "forward_lamp": ("tuning", forward_lamp),
    "forward_outside": ("tuning", forward_outside),
    "smoke": ("test", lambda res: mi.load_file(str(ROOT / "scenes" / "smoke.xml"),
                                               res=str(res))),
    "camera_inside": ("test", _inside),
    "forward_ball": ("test", lambda res: media_scene(homogeneous(3.0, albedo=0.95, g=0.9),
                                                     sensor=camera(res), env=0)),
    "chromatic_dense": ("test", lambda res: media_scene(
        homogeneous([8.0, 16.0, 30.0], albedo=0.95, g=0.3), sensor=camera(res), env=0.5)),
    "thin_ball": ("cost", lambda res: media_scene(homogeneous(0.2, albedo=0.8),
                                                  sensor=camera(res))),
    "near_empty_ball": ("cost", lambda res: media_scene(homogeneous(0.02, albedo=0.8),
                                                        sensor=camera(res))),
}
#: surfaces (``--surfaces``): path_rr against Mitsuba's path. The tuning scene chose
#: ``guiding_bins``, ``guiding_fraction`` and ``guiding_training``; ``slit_room`` and the
#: Cornell box were the scenes the lobes were first measured on.
SURFACE_SCENES = {
    "bounce_room": ("tuning", bounce_room),
    "door_room": ("test", door_room),
    "slit_room": ("test", slit_room),
    "cornell_box": ("test", lambda res: mi.load_file(str(ROOT / "scenes" / "cornell_box.xml"),
                                                     res=str(res))),
}


def selected(chosen: str, which: str) -> bool:
    """Whether a scene of set ``which`` runs under ``--set chosen`` (``both``: tuning and
    test)."""
    return chosen == which or (chosen == "both" and which in ("tuning", "test"))


def markdown(result: dict) -> str:
    cfg = result["config"]
    lines = ["# Path guiding: does it pay inside one render, training included?", "",
             f"Measured {result['date']} on {result['cpu']} ({result['variant']}) by "
             f"`python3 -m benchmarks.guiding {cfg['argv']}`: res {cfg['res']}, the built-in "
             f"(volpath; path for surfaces) at {cfg['spp']} spp, {cfg['runs']} alternating runs, reference {cfg['ref_spp']} "
             "spp. Efficiency ratio: ours / the built-in at equal time (90% bootstrap "
             "interval); relMSE/sample: ours / the built-in per sample (below 1: less "
             "variance). relMSE less the reference's own (`compare.reference_floor`: its "
             "standard error from the spread of its 256-spp renders), as `mitsuba-plugins "
             "compare` and docs/method.md section 1 define it; `raw`: the efficiency ratio "
             "with the reference's noise left in, as the tables of earlier sessions "
             "reported (it lowers the estimator with less variance most).", "",
             "| scene | set | " + " | ".join(cfg["configs"]) + " |",
             "|---|---|" + "---|" * len(cfg["configs"])]
    for name, r in result["scenes"].items():
        cells = []
        for c in cfg["configs"]:
            e = r["efficiency"][c]
            lo, hi = e["efficiency_ratio_90"]
            raw = f" (raw {e['efficiency_ratio_raw']:.2f}x)" if "efficiency_ratio_raw" in e else ""
            cells.append(f"{e['efficiency_ratio']:.2f}x [{lo:.2f}, {hi:.2f}]{raw}, "
                         f"{e['rel_mse_per_sample_ratio']:.2f}/sample, {e['spp']} spp"
                         f"{dense.guided_runs_note(e)}")
        lines.append(f"| {name} | {r['set']} | " + " | ".join(cells) + " |")
    counts = {c: [r["efficiency"][c].get("nan_inf_samples") for r in result["scenes"].values()]
              for c in cfg["configs"]}
    if all(v is not None for vs in counts.values() for v in vs):
        lines += ["", "NaN/Inf samples (zeroed and counted by the sample guard) in the timed "
                  "runs, all scenes: " + ", ".join(f"{c} {sum(v)}" for c, v in counts.items())
                  + "."]
    return "\n".join(lines) + "\n"


def picture(path: Path, res: int = 64, spp: int = 512) -> None:
    """The field learnt in the dense ball: for the cells of the slice through the ball's
    centre (8^3 cells), the lobe's axis projected on the slice, its length the mean
    cosine; the light's direction for comparison."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    scene = SCENES["dense_ball"][1](res)
    integrator = mi.load_dict({**CONFIGS["guided"], "max_depth": 64, "guiding_resolution": 8})
    mi.render(scene, integrator=integrator, spp=spp)
    f = integrator.guiding_report.field
    r = f.resolution
    W, V = f.sums[:, 0], f.sums[:, 1:4]
    drift = np.where((np.array(f.kappa) > 0)[:, None], V / np.maximum(W, 1e-30)[:, None], 0.0)
    k = r // 2                                   # the slice of cells at z = 0
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.add_patch(plt.Circle((0, 0), 1.0, fill=False, color="0.6"))
    for y in range(r):
        for x in range(r):
            idx = (k * r + y) * r + x
            cx, cy = (np.array([x, y]) + 0.5) / r * 2 - 1
            if f.records[idx] and np.hypot(cx, cy) < 1.1:
                ax.arrow(cx, cy, 0.6 * drift[idx, 0], 0.6 * drift[idx, 1], width=0.01,
                         color="C0" if np.array(f.kappa)[idx] > 0 else "0.7")
    light = np.array([1.6, 2.2])
    ax.annotate("light", xy=light / np.linalg.norm(light) * 1.25, color="C1")
    ax.set_xlim(-1.4, 1.4)
    ax.set_ylim(-1.4, 1.4)
    ax.set_aspect("equal")
    ax.set_title("Learnt lobes, dense ball (slice z = 0): axis x mean cosine")
    fig.savefig(path, dpi=110, bbox_inches="tight")


def _frozen_fields(args, scenes: dict, plain: dict, guiding: dict, resolutions, guides,
                   ref_variant=None) -> dict:
    """Per scene of ``scenes`` in ``--set``: the relMSE of unguided ``plain`` renders, then,
    per resolution, a field learnt by a ``--train``-spp render of ``plain`` with
    ``guiding`` (``guiding_training`` 0.9), frozen, and each pass of ``guides(field)``
    (``{key: GuidedPass}``) rendered at ``--spp``: its relMSE over the unguided one's (mean
    and standard error over ``--runs`` seeds), keyed ``r{resolution}_{key}``."""
    import numpy as np
    from mitsuba_plugins import guided_render
    rows = {}
    for name, (which, make) in scenes.items():
        if not selected(args.set, which):
            continue
        scene = make(args.res)
        ref = dense.reference(scene, args.ref_spp) if ref_variant is None else \
            dense.reference(scene, args.ref_spp, ref_variant)
        sensor = scene.sensors()[0]

        def rel(img):
            return stats.rel_mse(np.array(img)[..., :3], ref[..., :3])
        off = mi.load_dict(plain)
        base = [rel(mi.render(scene, integrator=off, spp=args.spp, seed=100 + s))
                for s in range(args.runs)]
        row = {"set": which, "off": [float(np.mean(base)), float(np.std(base) / np.sqrt(args.runs))]}
        for resolution in resolutions:
            integrator = mi.load_dict({**plain, **guiding, "guiding_resolution": resolution,
                                       "guiding_training": 0.9})
            # trained whatever its size (below MIN_TRAINING_PATHS a guided render is one
            # plain pass and learns no field; that rule is about time, not counted here)
            floor, guided_render.MIN_TRAINING_PATHS = guided_render.MIN_TRAINING_PATHS, 0
            try:
                mi.render(scene, integrator=integrator, spp=args.train, seed=1)
            finally:
                guided_render.MIN_TRAINING_PATHS = floor
            for key, guide in guides(guided_render, integrator.guiding_report.field).items():
                errs = [rel(guided_render._PassRender(integrator, sensor, guide).render(
                    scene, sensor, 100 + s, args.spp)) for s in range(args.runs)]
                ratio = np.array(errs) / np.mean(base)
                row[f"r{resolution}_{key}"] = [float(ratio.mean()),
                                               float(ratio.std() / np.sqrt(args.runs))]
        rows[name] = row
        print(name, row, flush=True)
    return rows


def ceiling(args) -> dict:
    """Relative MSE per sample of guided passes whose field was learnt beforehand (a
    ``--train``-spp render, its field then frozen) over that of unguided renders, at
    ``--spp`` samples, ``--runs`` seeds each (mean and standard error): the most that
    directional guiding with this field can give, training time not counted. 4^3 and 8^3
    cells, 4 and 16 candidates."""
    return _frozen_fields(
        args, SCENES, {"type": "volpath_delta"}, {"guiding": "volumes"}, (4, 8),
        lambda gr, field: {f"c{c}": gr.GuidedPass(field, True, False, c) for c in (4, 16)})


def surface_ceiling(args) -> dict:
    """``--ceiling --surfaces``: as :func:`ceiling` for ``path_rr``'s histograms on the
    surface scenes, against unguided ``path_rr``: 8^3 and 16^3 cells, sampled at
    ``guiding_fraction`` 0.2, 0.5 and 0.8. With ``--bins 16,32,64``: 8^3 cells with
    that many bins per axis (``guiding_bins``) instead, at fractions 0.2 and 0.5 (keys
    ``bB_fA``): how much finer directions could give."""
    plain = {"type": "path_rr", "max_depth": 12}
    if args.bins:
        rows = {}
        for bins in (int(b) for b in args.bins.split(",")):
            part = _frozen_fields(
                args, SURFACE_SCENES, plain, {"guiding": "surfaces", "guiding_bins": bins},
                (8,), lambda gr, field: {f"f{f:g}": gr.GuidedPass(field, True, False,
                                                                  fraction=f)
                                         for f in (0.2, 0.5)}, ref_variant=plain)
            for name, row in part.items():
                rows.setdefault(name, {"set": row["set"], "off": row["off"]}).update(
                    {f"b{bins}_{k[3:]}": v for k, v in row.items() if k.startswith("r8_")})
        return rows
    return _frozen_fields(
        args, SURFACE_SCENES, plain, {"guiding": "surfaces"}, (8, 16),
        lambda gr, field: {f"f{f:g}": gr.GuidedPass(field, True, False, fraction=f)
                           for f in (0.2, 0.5, 0.8)}, ref_variant=plain)


def sources(res: int = 64, spp: int = 8, runs: int = 16) -> dict:
    """Where the squared error of unguided ``volpath_delta`` lives, per scene: the share
    carried by the 2% largest squared deviations from the per-pixel mean over ``runs``
    renders of ``spp`` (fireflies), and the mean squared error against a 1024-spp
    reference of renders cut at max_depth 2 and 3, over that of unbounded ones."""
    import numpy as np
    rows = {}
    for name, (_, make) in SCENES.items():
        scene = make(res)
        integ = mi.load_dict({"type": "volpath_delta"})
        imgs = np.array([np.array(mi.render(scene, integrator=integ, spp=spp, seed=s))[..., :3]
                         .mean(-1) for s in range(runs)])
        z = np.sort(((imgs - imgs.mean(0)) ** 2).ravel())[::-1]
        row = {"top2_share": float(z[:int(0.02 * z.size)].sum() / z.sum())}
        mse = {}
        for depth in (2, 3, -1):
            cut = mi.load_dict({"type": "volpath_delta", "max_depth": depth})
            ref = np.array(mi.render(scene, integrator=cut, spp=1024, seed=999))[..., :3]
            mse[depth] = float(np.mean([np.mean((np.array(mi.render(
                scene, integrator=cut, spp=2 * spp, seed=s))[..., :3] - ref) ** 2)
                for s in range(runs // 2)]))
        row.update({f"depth{d}_over_all": mse[d] / mse[-1] for d in (2, 3)})
        rows[name] = row
        print(name, row, flush=True)
    return rows


def ceiling_markdown(result: dict) -> str:
    cfg = result["config"]
    surfaces = cfg.get("surfaces", False)
    keys = [k for k in next(iter(result["scenes"].values())) if k not in ("set", "off")]
    lines = ["# Path guiding " + ("at surfaces" if surfaces else "in media") +
             ": the most a frozen, well-trained field gives", "",
             f"Measured {result['date']} on {result['cpu']} ({result['variant']}) by "
             f"`python3 -m benchmarks.guiding {cfg['argv']}`: res {cfg['res']}, field learnt "
             f"by a {cfg['train']}-spp guided render, then frozen; {cfg['spp']} spp x "
             f"{cfg['runs']} seeds; reference {cfg['ref_spp']} spp. Entries: relMSE of the "
             "guided pass / relMSE of unguided " + ("path_rr" if surfaces else "volpath_delta") +
             " at the same spp (below 1: guiding lowers the variance per sample), +- standard "
             "error; " + ("rN_fA: N^3 cells, guiding_fraction A; bB_fA: 8^3 cells of BxB "
                          "directional bins" if surfaces else
                          "rN_cM: N^3 cells, M candidates") + ". Training time not counted.", "",
             "| scene | set | off relMSE | " + " | ".join(keys) + " |",
             "|---|---|---|" + "---|" * len(keys)]
    for name, r in result["scenes"].items():
        lines.append(f"| {name} | {r['set']} | {r['off'][0]:.4g} | " + " | ".join(
            f"{r[k][0]:.2f} +- {r[k][1]:.2f}" for k in keys) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--ref-spp", type=int, default=2048)
    ap.add_argument("--set", choices=("tuning", "test", "both", "cost"), default="both")
    ap.add_argument("--configs", default="off,guided")
    ap.add_argument("--scenes", default="", help="only these scenes (comma-separated)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "guiding"))
    ap.add_argument("--surfaces", action="store_true",
                    help="path_rr with and without guiding against path, on SURFACE_SCENES")
    ap.add_argument("--picture", action="store_true",
                    help="only draw the learnt field (docs/results/guiding_field.png)")
    ap.add_argument("--ceiling", action="store_true",
                    help="frozen, well-trained fields against unguided renders at equal spp")
    ap.add_argument("--train", type=int, default=2048, help="--ceiling: training spp")
    ap.add_argument("--bins", default="", help="--ceiling --surfaces: directional bins per "
                    "axis to compare (e.g. 16,32,64; 8^3 cells)")
    ap.add_argument("--sources", action="store_true",
                    help="where unguided volpath_delta's squared error lives (prints)")
    args = ap.parse_args()
    if args.sources:
        sources()
        return
    if args.ceiling:
        result = {"date": datetime.date.today().isoformat(),
                  "cpu": device_model(dense.VARIANT), "variant": dense.VARIANT,
                  "config": {"res": args.res, "spp": args.spp, "runs": args.runs,
                             "ref_spp": args.ref_spp, "train": args.train,
                             "surfaces": args.surfaces, "argv": " ".join(sys.argv[1:])}}
        result["scenes"] = surface_ceiling(args) if args.surfaces else ceiling(args)
        out = Path(args.out)
        output.write_json(out.with_suffix(".json"), result, indent=1)
        output.write_text(out.with_suffix(".md"), ceiling_markdown(result))
        print(ceiling_markdown(result))
        return
    if args.picture:
        picture(ROOT / "docs" / "results" / "guiding_field.png")
        return
    if args.surfaces and args.configs == "off,guided":
        args.configs = "path_rr,path_rr_guided"
    configs = {k: CONFIGS[k] for k in args.configs.split(",")}
    result = {"date": datetime.date.today().isoformat(), "cpu": device_model(dense.VARIANT),
              "variant": dense.VARIANT, "scenes": {},
              "config": {"res": args.res, "spp": args.spp, "runs": args.runs,
                         "ref_spp": args.ref_spp, "configs": list(configs),
                         "argv": " ".join(sys.argv[1:])}}
    out = Path(args.out)
    scenes = SURFACE_SCENES if args.surfaces else SCENES
    for name, (which, make) in scenes.items():
        if not selected(args.set, which) or \
                (args.scenes and name not in args.scenes.split(",")):
            continue
        scene = make(args.res)
        if args.surfaces:
            builtin = {"type": "path", "max_depth": 12}
            ref = dense.reference_estimate(scene, args.ref_spp, builtin)
            eff = dense.equal_time(scene, configs, args.spp, args.runs, ref, builtin)
        else:
            ref = dense.reference_estimate(scene, args.ref_spp)
            eff = dense.equal_time(scene, configs, args.spp, args.runs, ref)
        for k in configs:
            eff[k]["rel_mse_per_sample_ratio"] = (eff[k]["rel_mse"] * eff[k]["spp"]) / \
                (eff["builtin"]["rel_mse"] * eff["builtin"]["spp"])
        result["scenes"][name] = {"set": which, "efficiency": eff}
        print(name, ", ".join(f"{k} {eff[k]['efficiency_ratio']:.2f}x "
                              f"(relMSE/sample {eff[k]['rel_mse_per_sample_ratio']:.2f})"
                              for k in configs), flush=True)
        output.write_json(out.with_suffix(".json"), result, indent=1)
        output.write_text(out.with_suffix(".md"), markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
