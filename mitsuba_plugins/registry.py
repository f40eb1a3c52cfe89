"""Plugin registration across Mitsuba variants.

Each plugin module defines its class against the variant active at import time and
registers it on its last line, so a variant switch re-imports every module.
"""
from __future__ import annotations

import importlib
import os
import sys

import drjit as dr
import mitsuba as mi

from mitsuba_plugins import _llvm

#: registered name -> module that defines and registers it
PLUGINS = {
    "direct_mis": "mitsuba_plugins.integrators.direct_mis",
    "path_rr": "mitsuba_plugins.integrators.path_rr",
    "grid_medium": "mitsuba_plugins.media.grid_medium",
    "volpath_delta": "mitsuba_plugins.integrators.volpath_delta",
    "volpath_raymarch": "mitsuba_plugins.integrators.volpath_raymarch",
}
#: shared modules whose classes bind variant types at import; re-imported first
SUPPORT_MODULES = ("mitsuba_plugins.validity", "mitsuba_plugins.loop_state",
                   "mitsuba_plugins.tracking.majorant_grid",
                   "mitsuba_plugins.tracking.walk",
                   "mitsuba_plugins.tracking.null_collision",
                   "mitsuba_plugins.tracking.majorant",
                   "mitsuba_plugins.tracking.medium_protocol",
                   "mitsuba_plugins.tracking.trackers",
                   "mitsuba_plugins.tracking.homogeneous",
                   "mitsuba_plugins.tracking.transmittance",
                   "mitsuba_plugins.tracking.scene_media",
                   "mitsuba_plugins.tracking.replay",
                   "mitsuba_plugins.tracking.empty_scatter",
                   "mitsuba_plugins.tracking.free_flights",
                   "mitsuba_plugins.tracking.marching",
                   "mitsuba_plugins.guiding.sampling",
                   "mitsuba_plugins.path_loop",
                   "mitsuba_plugins.volume_loop", "mitsuba_plugins.differentiable",
                   "mitsuba_plugins.guided_render")
#: plugins that are not integrators, by kind
KINDS = {"grid_medium": "medium"}


#: Environment variable naming the variant that the CLI, the tests and the benchmarks use
#: by default (e.g. ``cuda_ad_rgb`` on a machine with an NVIDIA GPU).
VARIANT_VARIABLE = "MITSUBA_PLUGINS_VARIANT"


def default_variant() -> str:
    """``$MITSUBA_PLUGINS_VARIANT``, or ``llvm_ad_rgb`` when it is unset or empty."""
    return os.environ.get(VARIANT_VARIABLE) or "llvm_ad_rgb"


class UnsupportedVariantError(RuntimeError):
    """The active Mitsuba variant cannot run these plugins."""


def check_variant(variant: str | None) -> None:
    """Raise a clear error unless ``variant`` is a JIT, unpolarized variant."""
    if variant is None:
        raise UnsupportedVariantError(
            "mitsuba_plugins: no Mitsuba variant is set; call mi.set_variant('llvm_ad_rgb') "
            "(or another llvm_*/cuda_* variant) first.")
    if not (variant.startswith("llvm_") or variant.startswith("cuda_")):
        raise UnsupportedVariantError(
            f"mitsuba_plugins: variant '{variant}' is not supported: the plugins are "
            "vectorised Dr.Jit code and need a JIT variant (llvm_* or cuda_*, e.g. "
            "'llvm_ad_rgb').")
    if "polarized" in variant:
        raise UnsupportedVariantError(
            f"mitsuba_plugins: variant '{variant}' is not supported: polarized rendering "
            "is not implemented; use the unpolarized variant (e.g. 'llvm_ad_rgb').")
    if variant.startswith("llvm_"):
        if not os.environ.get(_llvm.ENV_VAR) and "drjit" not in sys.modules:
            _llvm.choose_llvm()  # raises with the fix
        _llvm.check_loaded_llvm(tuple(dr.detail.llvm_version()))


def _register_refusal(error: Exception) -> None:
    """In an unsupported variant, make each plugin name fail with our message."""
    def refuse(props, _error=error):
        raise _error
    for name in PLUGINS:
        register_kind = {"integrator": mi.register_integrator,
                         "medium": mi.register_medium}[KINDS.get(name, "integrator")]
        register_kind(name, refuse)


def register() -> None:
    """Register every plugin in the active variant (re-importing after a switch).

    Raises :class:`UnsupportedVariantError` for scalar or polarized variants.
    """
    variant = mi.variant()
    check_variant(variant)
    for module_name in (*SUPPORT_MODULES, *PLUGINS.values()):
        module = sys.modules.get(module_name)
        if module is None:
            importlib.import_module(module_name)
        elif getattr(module, "VARIANT", None) != variant:
            importlib.reload(module)


def _on_variant_change(old: str | None, new: str | None) -> None:
    if new is None:
        return
    try:
        check_variant(new)
    except UnsupportedVariantError as error:
        # Switching to a scalar variant for other work is legal; using our plugins
        # there is not, and says why.
        _register_refusal(error)
        return
    register()


def _install_callback() -> None:
    if getattr(mi, "_mitsuba_plugins_callback", False):
        return
    mi.detail.add_variant_callback(_on_variant_change)
    mi._mitsuba_plugins_callback = True
    if mi.variant() is not None:
        register()


register.install_callback = _install_callback
