"""The procedural cloud of the sparse-storage benchmarks (NumPy only: Debian's Python
imports it too, to write the cloud as .vdb through pyopenvdb).

Five Gaussian puffs with a sinusoidal ripple, thresholded: about 3.9% of an n^3 box
active, all in its central 56% per axis."""
import numpy as np

PUFFS = [(0.5, 0.5, 0.5, 0.17), (0.36, 0.55, 0.45, 0.11), (0.64, 0.47, 0.55, 0.12),
         (0.5, 0.62, 0.4, 0.1), (0.45, 0.4, 0.62, 0.09)]


def extent(n: int) -> tuple:
    """Index range ``[lo, hi)`` (every axis) outside which the cloud is 0."""
    return int(0.22 * n), int(0.78 * n)


def cloud_slices(n: int):
    """Yield ``(k, slice)``: z-slice ``k`` of the cloud over ``extent(n)`` on y and x,
    a float32 ``(y, x)`` array."""
    lo, hi = extent(n)
    c = (np.arange(lo, hi, dtype=np.float32) + 0.5) / n
    Y, X = np.meshgrid(c, c, indexing="ij")
    for k in range(lo, hi):
        z = (k + 0.5) / n
        f = np.zeros_like(X)
        for px, py, pz, r in PUFFS:
            f += np.exp(-((X - px) ** 2 + (Y - py) ** 2 + (z - pz) ** 2) / (2 * r * r))
        f += 0.18 * np.sin(X * 61.0 + 1.3) * np.sin(Y * 57.0) * np.sin(z * 67.0 + 0.4)
        yield k, np.clip((f - 1.08) * 3.0, 0.0, None).astype(np.float32)


def write_npy(n: int, path) -> None:
    """The cloud as an n^3 ``(Z, Y, X)`` .npy, slice by slice."""
    lo, hi = extent(n)
    out = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=(n, n, n))
    for k, d in cloud_slices(n):
        out[k, lo:hi, lo:hi] = d
    out.flush()
    del out


def scene_dict(medium: dict, res: int, mi) -> dict:
    """The benchmark scene: the medium in the cube [-1, 1]^3, sun and sky."""
    return {
        "type": "scene",
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 0.3}},
        "sun": {"type": "directional", "direction": [-1, -1, -0.5],
                "irradiance": {"type": "rgb", "value": 3.0}},
        "box": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0.5, 4.2], [0, 0, 0],
                                                              [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res},
                   "sampler": {"type": "independent"}},
    }
