"""Generate ``data/fire.vdb`` for ``fire.xml``: a burning plume as a simulation writes it.

Run from anywhere: ``python scenes/make_fire.py``. Deterministic (fixed seed). The file
holds two half-float grids as Houdini / EmberGen export them: ``density`` (smoke, 0..1)
and ``temperature`` (in kilokelvin above ambient: ``temperature_scale = 1000`` in the
scene; the core reaches about 2.4 kK, the smoke's edge cools below the 100 K cutoff). Written through Debian's ``python3-openvdb`` (:mod:`mitsuba_plugins.grids.vdb_openvdb`), with
Blosc or zip compression as that build defaults.
"""
from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # run from a checkout without installing
from mitsuba_plugins.grids.vdb_openvdb import DEFAULT_PYTHON  # noqa: E402


def plume(seed: int = 11):
    """``(density, temperature)`` ``(X, Y, Z)`` arrays (OpenVDB's index order): a
    turbulent column rising from a hot base, hottest low in its core."""
    from scipy.ndimage import gaussian_filter
    rng = np.random.default_rng(seed)
    nx, ny, nz = 48, 64, 48                     # y is up
    x, y, z = np.meshgrid(np.linspace(-1, 1, nx), np.linspace(0, 1, ny),
                          np.linspace(-1, 1, nz), indexing="ij")
    noise = gaussian_filter(rng.normal(size=x.shape), 2.5)
    noise /= np.abs(noise).max()
    sway = 0.15 * np.sin(5.0 * y) + 0.2 * noise
    radius = 0.25 + 0.45 * y
    r2 = ((x - sway) ** 2 + (z - 0.5 * sway) ** 2) / radius ** 2
    density = np.clip(np.exp(-2.0 * r2) * (1.0 + 0.6 * noise) * (1.05 - 0.6 * y), 0, None)
    density[density < 0.02] = 0.0
    core = np.exp(-2.0 * r2) * np.clip(1.0 - 0.9 * y, 0, None) * (1.0 + 0.3 * noise)
    temperature = np.where(density > 0, 2.6 * np.clip(core, 0, None), 0.0)
    return density.astype(np.float32), temperature.astype(np.float32)


def main() -> None:
    density, temperature = plume()
    out = HERE / "data" / "fire.vdb"
    with tempfile.TemporaryDirectory() as tmp:
        np.save(f"{tmp}/density.npy", density)
        np.save(f"{tmp}/temperature.npy", temperature)
        script = f"""
import numpy as np, pyopenvdb as vdb
grids = []
for name in ("density", "temperature"):
    g = vdb.FloatGrid(); g.name = name
    g.copyFromArray(np.load("{tmp}/" + name + ".npy"), tolerance=0.0)
    g.transform = vdb.createLinearTransform(voxelSize=1.0 / 32)
    g.saveFloatAsHalf = True
    g.gridClass = vdb.GridClass.FOG_VOLUME
    grids.append(g)
vdb.write("{out}", grids=grids)
"""
        subprocess.run([DEFAULT_PYTHON, "-c", script], check=True)
    print(f"wrote {out}: {int((density > 0).sum())} active density voxels, "
          f"temperature up to {temperature.max() * 1000:.0f} K")


if __name__ == "__main__":
    main()
