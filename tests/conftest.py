"""Test configuration: a working LLVM is chosen (mitsuba_plugins first), the test variant
(``$MITSUBA_PLUGINS_VARIANT``, default llvm_ad_rgb; cuda_ad_rgb on a GPU) is active, and
every plugin is registered. ``--jit-debug`` turns on Dr.Jit's debug mode (out-of-bounds
gathers become errors). Tests that are about the LLVM backend itself carry
``@pytest.mark.llvm_only`` and are skipped, with that reason, in a CUDA variant."""
import mitsuba_plugins  # noqa: F401  -- must precede drjit: picks libLLVM

import drjit as dr
import mitsuba as mi
import pytest

from mitsuba_plugins.registry import default_variant  # noqa: E402

VARIANT = default_variant()


def pytest_addoption(parser):
    parser.addoption("--jit-debug", action="store_true",
                     help="enable dr.JitFlag.Debug (bounds-checked gathers, slower)")


def pytest_configure(config):
    mi.set_variant(VARIANT)
    config.addinivalue_line("markers", "llvm_only: tests Dr.Jit's LLVM backend itself")
    if config.getoption("--jit-debug"):      # any backend (it once applied to CUDA only)
        dr.set_flag(dr.JitFlag.Debug, True)


def pytest_collection_modifyitems(config, items):
    if VARIANT.startswith("llvm_"):
        return
    skip = pytest.mark.skip(reason=f"about the LLVM backend; the test variant is {VARIANT}")
    for item in items:
        if "llvm_only" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(autouse=True)
def variant(request):
    """Every test starts in the test variant with the plugins registered and a clean JIT;
    a test that asks for the ``other_variant`` fixture (tests/integrators/test_spectral_and_mono.py, module
    scope) starts in that one. The switch happens only where the variant changes: each
    switch re-imports the plugin modules, and tests are grouped by variant."""
    wanted = request.getfixturevalue("other_variant") \
        if "other_variant" in request.fixturenames else VARIANT
    if mi.variant() != wanted:
        mi.set_variant(wanted)
    yield wanted
    dr.sync_thread()


@pytest.fixture(autouse=True, scope="module")
def _fresh_kernels_per_module():
    """Every test module starts without the kernels earlier modules compiled. Dr.Jit 1.5's
    LLVM backend can abort a kernel ("invalid redefinition of function") depending on
    what the process compiled before (docs/validation.md): on 2026-11-27 the whole
    spectral and mono suites aborted in tests/integrators/test_gradients.py, which passed
    alone and after tests/guiding/. Kernels come back from Dr.Jit's disk cache. A
    workaround, not a fix: the bug is Dr.Jit's."""
    dr.flush_kernel_cache()
    yield
