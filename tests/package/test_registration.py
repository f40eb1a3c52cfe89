"""Registration follows variant switches; scalar variants say why they cannot work; the
package's import graph (no circles, no tooling in the core); the ``--jit-debug`` option."""
import ast
import subprocess
import sys
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mitsuba_plugins
from helpers import load
from conftest import VARIANT


def test_plugins_registered_in_active_variant():
    kinds = {"integrator": mi.SamplingIntegrator, "medium": mi.Medium}
    for name in mitsuba_plugins.PLUGINS:
        kind = mitsuba_plugins.registry.KINDS.get(name, "integrator")
        assert isinstance(mi.load_dict({"type": name}), kinds[kind])


def test_switch_to_scalar_gives_clear_error():
    mi.set_variant("scalar_rgb")
    with pytest.raises(RuntimeError, match="needs a JIT variant|is not supported: the plugins are vectorised"):
        mi.load_dict({"type": "path_rr"})
    with pytest.raises(RuntimeError, match="need a JIT variant"):
        mi.load_dict({"type": "grid_medium"})
    with pytest.raises(mitsuba_plugins.UnsupportedVariantError, match="llvm_\\* or cuda_\\*"):
        mitsuba_plugins.register()


def test_switch_variant_and_render():
    """From the test variant to another of the same backend (mono; rgb where the test
    variant is mono) and back: the plugins render in both."""
    backend = VARIANT.split("_", 1)[0]
    other = f"{backend}_ad_rgb" if VARIANT.endswith("_mono") else f"{backend}_ad_mono"
    for variant in (other, VARIANT):
        mi.set_variant(variant)
        channels = 1 if mi.is_monochromatic else 3
        for name in ("direct_mis", "path_rr"):
            img = np.array(mi.render(load("furnace_env", integrator=name, res=8), spp=16))
            assert img.shape == (8, 8, channels) and np.all(np.isfinite(img))
            assert abs(img.mean() - 0.8) < 0.05, (variant, name, img.mean())
        assert isinstance(mi.load_dict({"type": "grid_medium"}), mi.Medium)  # issue 24


def _core_files():
    root = Path(__file__).resolve().parents[2]
    core = [p for p in (root / "mitsuba_plugins").rglob("*.py") if "tools" not in p.parts]
    return core + list((root / "integrators").glob("*.py")) + list((root / "media").glob("*.py"))


def test_core_never_imports_tooling():
    """docs/architecture.md: plugins and the core import no evaluation tooling."""
    offenders = []
    for path in _core_files():
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            if any(n.startswith("mitsuba_plugins.tools") for n in names):
                offenders.append(path.name)
    assert offenders == []


def test_variant_bound_modules_are_registered():
    """docs/architecture.md rule 1: a core module that binds variant types at import
    (``VARIANT = mi.variant()`` or a ``DRJIT_STRUCT`` class) is re-imported on a variant
    switch, so it must be listed in registry.SUPPORT_MODULES."""
    from mitsuba_plugins.registry import SUPPORT_MODULES
    root = Path(__file__).resolve().parents[2]
    bound = {_module_name(p, root) for p in _core_files()
             if p.parent.name not in ("integrators", "media")
             and ("DRJIT_STRUCT" in p.read_text() or "VARIANT = mi.variant()" in p.read_text())}
    assert bound - set(SUPPORT_MODULES) == set()


def _module_name(path: Path, root: Path) -> str:
    rel = path.relative_to(root).with_suffix("")
    parts = list(rel.parts)
    if parts[0] in ("integrators", "media"):
        parts = ["mitsuba_plugins", *parts]
    return ".".join(p for p in parts if p != "__init__")


def test_no_import_circles():
    """Issue 25: no two modules of the package import each other, directly or through
    others, anywhere in their text (imports inside functions included: a circle hidden
    that way still ties the two modules together)."""
    root = Path(__file__).resolve().parents[2]
    files = _core_files() + list((root / "mitsuba_plugins" / "tools").glob("*.py"))
    modules = {_module_name(p, root): p for p in files}
    graph = {}
    for name, path in modules.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            found = []
            if isinstance(node, ast.ImportFrom) and node.module:   # a submodule, else the module
                found = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules
                         else node.module for a in node.names]
            elif isinstance(node, ast.Import):
                found = [a.name for a in node.names]
            targets |= {f for f in found if f in modules and f != name}
        graph[name] = targets
    state, circles = {}, []

    def visit(node, stack):
        state[node] = "open"
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                circles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = "done"
    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    assert circles == [], " ; ".join(" -> ".join(c) for c in circles)


def test_jit_debug_flag_follows_the_option(pytestconfig):
    """``--jit-debug`` turns on Dr.Jit's debug mode in every backend (issue 25: conftest
    returned before reading it on LLVM); without it the mode is off."""
    assert bool(dr.flag(dr.JitFlag.Debug)) == bool(pytestconfig.getoption("--jit-debug"))


def test_jit_debug_option_reaches_llvm(tmp_path):
    """The same test run with ``--jit-debug`` in a child pytest (LLVM by default)."""
    here = Path(__file__).resolve()
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--jit-debug",
         f"{here}::test_jit_debug_flag_follows_the_option"],
        capture_output=True, text=True, timeout=300, cwd=here.parents[2])
    assert proc.returncode == 0 and "1 passed" in proc.stdout, proc.stdout[-2000:]


#: docs/architecture.md's layers, bottom first: a module imports its own layer or below
LAYERS = ("base", "grids", "tracking", "loops", "plugins", "tools")
LOOPS = ("path_vertex", "path_loop", "volume_loop", "differentiable", "guided_render")


def _layer(module: str) -> str:
    parts = module.split(".")
    if len(parts) > 1 and parts[1] in ("grids", "tracking", "tools"):
        return parts[1]
    if len(parts) > 1 and parts[1] == "guiding":      # the field: beside tracking
        return "tracking"
    if len(parts) > 1 and parts[1] in ("integrators", "media"):
        return "plugins"
    return "loops" if len(parts) > 1 and parts[1] in LOOPS else "base"


def test_imports_run_down_the_layers():
    """Issue 49: grids never import tracking, tracking never imports the loops, the base
    (params, validity, instrument, output, mis, registry) imports none of them; checked on
    every import of the package's own modules, inside functions too."""
    root = Path(__file__).resolve().parents[2]
    files = _core_files() + list((root / "mitsuba_plugins" / "tools").glob("*.py"))
    modules = {_module_name(p, root) for p in files}
    upward = []
    for path in files:
        name = _module_name(path, root)
        for node in ast.walk(ast.parse(path.read_text())):
            targets = []
            if isinstance(node, ast.ImportFrom) and node.module:
                targets = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules
                           else node.module for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            for target in targets:
                if target in modules and target != "mitsuba_plugins" and \
                        LAYERS.index(_layer(target)) > LAYERS.index(_layer(name)):
                    upward.append(f"{name} -> {target}")
    assert upward == []
