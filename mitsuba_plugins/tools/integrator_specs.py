"""Integrators as the tooling names them: ``name:key=value`` specifications and their
labels, the Mitsuba built-in each of our plugins is measured against (its *twin*, with
the parameters it understands), what an integrator leaves out of a scene (a medium's
emission, media altogether) and the reference that renders everything it is compared on."""
from __future__ import annotations

#: Our plugin -> the Mitsuba built-in that estimates the same quantity, and the
#: parameters of ours that the built-in understands (passed on to the reference).
BUILTIN = {"direct_mis": "direct", "path_rr": "path", "volpath_delta": "volpath",
           "volpath_raymarch": "volpath"}


BUILTIN_PARAMS = {
    "direct": ("shading_samples", "emitter_samples", "bsdf_samples", "hide_emitters"),
    "path": ("max_depth", "rr_depth", "hide_emitters"),
    "volpath": ("max_depth", "rr_depth", "hide_emitters"),
}


def is_ours(plugin_type: str) -> bool:
    """Whether ``plugin_type`` is one of this package's plugins (the registry decides:
    a Mitsuba integrator missing from :data:`BUILTIN`, e.g. ``volpathmis``, is not ours)."""
    from mitsuba_plugins.registry import PLUGINS
    return plugin_type in PLUGINS


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
        if key in out:
            raise ValueError(f"integrator option '{key}' is given twice in '{spec}'; allowed: "
                             "each option once")
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


def builtin_twin(integrator: dict) -> dict:
    """The built-in row an integrator's ratios are taken against (itself for a built-in)."""
    name = integrator["type"]
    builtin = BUILTIN.get(name, name)
    return {"type": builtin,
            **{k: v for k, v in integrator.items() if k in BUILTIN_PARAMS.get(builtin, ())}}


#: integrators that render participating media but not a medium's own emission
#: (Mitsuba's ``volpath`` family calls no ``get_radiance``)
NO_MEDIUM_EMISSION = ("volpath", "volpathmis", "prbvolpath")


#: integrators that render surfaces only: a medium's boundary is passed through
SURFACES_ONLY = ("path", "direct", "prb", "direct_projective", "prb_basic", "path_rr",
                 "direct_mis")


#: what renders every part of a scene that the integrators above can leave out
CAPABLE = "volpath_delta"


def ignores(scene, integrator_type: str) -> str:
    """The part of ``scene`` that an integrator of ``integrator_type`` does not render
    (``""``: none): participating media (surface integrators), or a medium's emission
    (``emission``, ``emission_grid``, ``temperature_grid``: Mitsuba's volumetric
    built-ins)."""
    from mitsuba_plugins.tracking.scene_media import scene_media
    media = scene_media(scene)
    if integrator_type in SURFACES_ONLY and media:
        return "participating media"
    if integrator_type in NO_MEDIUM_EMISSION and \
            any(getattr(m, "has_emission", False) for m in media):
        return "medium emission"
    return ""


#: a loaded integrator's plugin name, by the class Mitsuba reports for it
_CLASS_NAMES = {"VolumetricPathIntegrator": "volpath", "VolpathMisIntegratorImpl": "volpathmis",
                "PathIntegrator": "path", "DirectIntegrator": "direct", "PRBIntegrator": "prb",
                "PRBVolpathIntegrator": "prbvolpath", "DirectMIS": "direct_mis",
                "PathRR": "path_rr"}


def plugin_name(integrator) -> str:
    """The plugin name of a loaded integrator (``""`` where unknown)."""
    name = getattr(integrator, "NAME", None)
    if name:
        return name
    return _CLASS_NAMES.get(integrator.class_name(), _CLASS_NAMES.get(
        type(integrator).__name__, ""))


def reference_for(integrator: dict, scene=None) -> dict:
    """The built-in integrator (with the parameters it shares) that serves as reference;
    where it ignores part of ``scene`` (medium emission, media), :data:`CAPABLE` with
    the same shared parameters."""
    twin = builtin_twin(integrator)
    if twin["type"] not in BUILTIN_PARAMS:
        raise ValueError(f"no reference known for integrator '{integrator['type']}'; known: "
                         f"{', '.join(sorted(set(BUILTIN) | set(BUILTIN_PARAMS)))}; or give "
                         "--reference")
    if scene is not None and ignores(scene, twin["type"]):
        return {**twin, "type": CAPABLE}
    return twin


def check_reference(reference: dict, scene, scene_path: str) -> None:
    """Refuse, in one line, a reference that leaves part of the scene out."""
    missing = ignores(scene, reference["type"])
    if missing:
        raise ValueError(f"--reference {label(reference)} ignores the {missing} of "
                         f"{scene_path}, so every error against it would be wrong; use one "
                         f"that renders it (e.g. {CAPABLE} or volpath_raymarch)")
