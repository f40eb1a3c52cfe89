"""Scene files for the tooling: loading with a resolution, and a digest of a scene and
every file it names (what the reference caches key on). Kept apart so that
:mod:`~mitsuba_plugins.tools.compare` and :mod:`~mitsuba_plugins.tools.reference` both
import it rather than each other."""
from __future__ import annotations

import hashlib
import xml.etree.ElementTree as ET
from pathlib import Path


def load_scene(path: str, res: int | None = None):
    import mitsuba as mi
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
