"""Test configuration: a working LLVM is chosen (mitsuba_plugins first), the llvm_ad_rgb
variant is active, and every plugin is registered. ``--jit-debug`` turns on Dr.Jit's
debug mode (out-of-bounds gathers become errors)."""
import mitsuba_plugins  # noqa: F401  -- must precede drjit: picks libLLVM

import drjit as dr
import mitsuba as mi
import pytest

VARIANT = "llvm_ad_rgb"


def pytest_addoption(parser):
    parser.addoption("--jit-debug", action="store_true",
                     help="enable dr.JitFlag.Debug (bounds-checked gathers, slower)")


def pytest_configure(config):
    mi.set_variant(VARIANT)
    if config.getoption("--jit-debug"):
        dr.set_flag(dr.JitFlag.Debug, True)


@pytest.fixture(autouse=True)
def variant():
    """Every test starts in llvm_ad_rgb with the plugins registered and a clean JIT."""
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    yield VARIANT
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    dr.sync_thread()
