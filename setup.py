"""The optional compiled part: mitsuba_plugins.grids._openvdb_bricks, a leaf-level .vdb reader
against Debian's libopenvdb-dev (mitsuba_plugins/grids/_openvdb_bricks.cpp). Everything else is
declared in pyproject.toml. Without OpenVDB's headers the build of this one module fails
quietly (``optional``) and .vdb files are read by the pyopenvdb worker process instead."""
from setuptools import Extension, setup


def _extension() -> list:
    try:
        import pybind11
    except ImportError:          # built without build isolation and no pybind11: skip
        return []
    return [Extension(
        "mitsuba_plugins.grids._openvdb_bricks", ["mitsuba_plugins/grids/_openvdb_bricks.cpp"],
        include_dirs=[pybind11.get_include()], libraries=["openvdb", "tbb"],
        extra_compile_args=["-std=c++17", "-O2"], language="c++", optional=True)]


setup(ext_modules=_extension())
