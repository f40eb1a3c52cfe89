"""Scenes for the tooling: loading a scene file with a resolution, a digest of a scene and
every file it names (what the reference caches key on), and the small scenes built in
code that the tests and the benchmarks share (:func:`media_scene`, :func:`camera`,
:func:`homogeneous`, :func:`grid`). Kept apart so that
:mod:`~mitsuba_plugins.tools.compare` and :mod:`~mitsuba_plugins.tools.reference` both
import it rather than each other."""
from __future__ import annotations

import hashlib
import xml.etree.ElementTree as ET
from pathlib import Path

import mitsuba as mi


def load_scene(path: str, res: int | None = None):
    if Path(path).is_dir():
        raise FileNotFoundError(f"scene '{path}' is a folder; give a scene file (.xml)")
    if not Path(path).is_file():
        raise FileNotFoundError(f"scene file not found: {path}")
    params = {"res": str(res)} if res else {}
    return mi.load_file(str(path), **params)


def scene_digest(scene_path: str) -> str:
    """SHA-256 of the scene file and of every file it names (``filename`` parameters,
    ``<include>``), so that a changed grid or mesh invalidates cached references."""
    path = Path(scene_path)
    digest = hashlib.sha256(path.read_bytes())
    try:
        elements = list(ET.parse(path).iter())
    except ET.ParseError:
        elements = []
    for el in elements:
        name = el.get("filename") if el.tag == "include" else (
            el.get("value") if el.get("name") == "filename" else None)
        dep = path.parent / name if name else None
        if dep is not None and dep.is_file():
            digest.update(name.encode() + b"\0" + hashlib.sha256(dep.read_bytes()).digest())
    return digest.hexdigest()


#: the repository's scene folder and the grids the built scenes use
SCENES = Path(__file__).resolve().parents[2] / "scenes"
SMOKE = str(SCENES / "data" / "smoke.vol")
SPARSE = str(SCENES / "data" / "sparse.vol")


def camera(res=32, origin=(0.0, 0.6, 4.0), fov=38.0, medium=None, target=(0.0, 0.0, 0.0)):
    """A perspective sensor looking at ``target`` (optionally inside ``medium``)."""
    cam = {"type": "perspective", "fov": fov,
           "to_world": mi.ScalarTransform4f().look_at(list(origin), list(target), [0, 1, 0]),
           "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
           "sampler": {"type": "independent", "sample_count": 16}}
    if medium is not None:
        cam["medium"] = medium
    return cam


def media_scene(medium=None, bsdf=None, extra=None, sensor=None, env=0.4, as_dict=False):
    """A unit sphere holding ``medium`` behind ``bsdf`` (null by default) over a
    diffuse floor, lit by a small spherical light and a constant environment (loaded,
    or its description with ``as_dict``); ``env=0``: no environment (a constant of
    radiance 0 cannot be built in spectral variants: "no probability mass found")."""
    scene = {
        "type": "scene",
        "light": {"type": "sphere", "center": [1.6, 2.2, 1.2], "radius": 0.25,
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 40.0}}},
        "floor": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([0, -1.05, 0]).rotate(
                      [1, 0, 0], -90).scale(4),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}},
        "sensor": sensor or camera(),
    }
    if env:
        scene["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": env}}
    if medium is not None:
        scene["ball"] = {"type": "sphere", "bsdf": bsdf or {"type": "null"}, "interior": medium}
    scene.update(extra or {})
    return scene if as_dict else mi.load_dict(scene)


def homogeneous(sigma_t, albedo=0.8, g=None):
    medium = {"type": "homogeneous", "sigma_t": sigma_t, "albedo": albedo}
    if isinstance(sigma_t, list):  # rgb values must be <= 1: normalise, move the max to scale
        medium["sigma_t"] = {"type": "rgb", "value": [s / max(sigma_t) for s in sigma_t]}
        medium["scale"] = max(sigma_t)
    if g is not None:
        medium["phase"] = {"type": "hg", "g": g}
    return medium


def grid(filename=SMOKE, scale=8.0, albedo=0.85, to_world=None, **kw):
    medium = {"type": "grid_medium", "filename": filename, "scale": scale, "albedo": albedo,
              "to_world": to_world or mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)}
    medium.update(kw)
    return medium
