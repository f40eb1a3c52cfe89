"""Mitsuba 3 light-transport plugins written in Python against Dr.Jit.

Importing this package registers every plugin in the active JIT variant and, through
Mitsuba's variant-change callback, in every JIT variant set later::

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import mitsuba_plugins            # direct_mis, path_rr, ... are now registered

Importing it *before* ``mitsuba``/``drjit`` also points Dr.Jit at a working libLLVM
(see :mod:`mitsuba_plugins._llvm`).
"""
from __future__ import annotations

from mitsuba_plugins import _llvm

# Must happen before the first `import drjit` anywhere in the process.
_LLVM_PATH = _llvm.configure_environment()

from mitsuba_plugins.registry import PLUGINS, UnsupportedVariantError, register  # noqa: E402

__version__ = "0.1.0"
__all__ = ["PLUGINS", "UnsupportedVariantError", "register", "__version__"]

register.install_callback()
