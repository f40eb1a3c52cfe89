"""``mitsuba-plugins grid info``: what a grid file holds and what it will cost."""
from __future__ import annotations

import os

import numpy as np

from mitsuba_plugins.grids.gridio import iter_slabs, read_header, world_box


def _vdb_grids(path) -> list:
    from mitsuba_plugins.grids.vdb_openvdb import vdb_info
    keys = ("name", "address", "type", "readable", "active_voxels", "index_min", "index_max",
            "min", "max")
    return [{k: g.get(k) for k in keys} | ({"reason": g["reason"]} if not g["readable"]
                                             else {}) for g in vdb_info(path)]


def grid_info(path, cells: int = 16, grid: str | None = None) -> dict:
    """Summary of a grid file, read slab by slab: shape, bounds, density statistics,
    the fraction of majorant-grid volume (``cells`` per axis) whose bound is 0, and the
    memory its (dense) storage takes; for a ``.vdb``, every grid of the file and the
    world bounds from its transform.

    ``grid``: which grid of a ``.vdb`` to read (a name, or ``name[k]``). When not given
    (``density``) and the file has no single grid of that name, the summary lists the
    file's grids only (``grid`` None, ``note`` says why)."""
    from mitsuba_plugins.grids.bricks import SIDE, BrickBuilder
    from mitsuba_plugins.grids.gridio import GridFileError
    from mitsuba_plugins.grids.bounds import MajorantBuilder, resolution_for
    try:
        header = read_header(path, grid or "density")
    except GridFileError as error:
        if grid is not None or not os.fspath(path).lower().endswith(".vdb"):
            raise
        grids = _vdb_grids(path)         # a file that cannot be listed raises here
        reason = str(error).split("': ", 1)[-1]
        return {"file": os.fspath(path), "format": "vdb", "grid": None,
                "note": f"{reason}; read one with --grid ADDRESS", "vdb_grids": grids}
    z, y, x, c = header.shape
    builder = MajorantBuilder(header.shape, resolution_for(header.shape, cells))
    bricks = BrickBuilder(header.shape, keep_blocks=False)
    total, vmin, vmax, nonfinite = 0.0, np.inf, 0.0, 0
    for z0, slab in iter_slabs(header):
        finite = np.isfinite(slab)
        nonfinite += int((~finite).sum())
        slab = np.where(finite, slab, 0.0).astype(np.float32)
        total += float(slab.sum(dtype=np.float64))
        vmin, vmax = min(vmin, float(slab.min())), max(vmax, float(slab.max()))
        builder.add(z0, slab)
        bricks.add(z0, slab)
    mean = total / header.size
    cells_max = builder.finish()
    lo, hi, _ = world_box(header)
    bbox, bbox_from, extra = (lo, hi), "header" if header.bbox else "unit cube", {}
    if header.vdb_grid is not None:
        bbox_from = "index-to-world transform (active box + 1 voxel)"
        extra = {"grid": header.vdb_grid, "index_min": list(header.index_min),
                 "vdb_grids": _vdb_grids(path)}
    return {
        "file": header.path,
        "format": os.path.splitext(header.path)[1][1:],
        "resolution": [x, y, z],
        "channels": c,
        "bbox_min": list(bbox[0]),
        "bbox_max": list(bbox[1]),
        "bbox_from": bbox_from,
        "min": vmin,
        "max": vmax,
        "mean": mean,
        "max_over_mean": vmax / mean if mean > 0 else float("inf"),
        "nonfinite": nonfinite,
        "negative": vmin < 0,
        "majorant_resolution": list(builder.resolution),
        "majorant_empty_fraction": float(np.mean(cells_max == 0)),
        "majorant_mean_over_max": float(cells_max.mean() / vmax) if vmax > 0 else 0.0,
        "storage_bytes": 4 * header.size,
        "sparse_bricks": bricks.stored - 1,
        "sparse_storage_bytes": 4 * (bricks.index.size + bricks.stored * SIDE ** 3 * c),
        **extra,
    }


def _grid_lines(info: dict) -> list:
    lines = []
    for g in info.get("vdb_grids", []):
        mark = " (read)" if g["address"] == info.get("grid") else ""
        if not g["readable"]:
            lines.append((f"grid {g['address']!r}", f"{g['type']}: not readable here "
                                                   f"({g['reason']})"))
            continue
        box = (f"index {g['index_min']} - {g['index_max']}" if g["index_min"] is not None
               else "no active voxels")
        lines.append((f"grid {g['address']!r}{mark}", f"{g['type']}, {g['active_voxels']} "
                                                      f"active voxels, {box}, values "
                                                      f"{g['min']} - {g['max']}"))
    return lines


def _aligned(lines: list) -> str:
    width = max(len(k) for k, _ in lines)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in lines)


def format_info(info: dict) -> str:
    """``grid_info`` as aligned text lines."""
    if info.get("grid", "") is None:                # a .vdb listed, no grid read
        return _aligned([("file", info["file"]), ("format", "vdb"),
                         *_grid_lines(info), ("note", info["note"])])
    res = " x ".join(map(str, info["resolution"]))
    mres = " x ".join(map(str, info["majorant_resolution"]))
    fmt = lambda v: "[" + ", ".join(f"{a:g}" for a in v) + "]"  # noqa: E731
    lines = [
        ("file", info["file"]),
        ("resolution", f"{res} (X x Y x Z), {info['channels']} channel(s), {info['format']}"),
        ("bounds", f"{fmt(info['bbox_min'])} - {fmt(info['bbox_max'])} ({info['bbox_from']})"),
        ("storage", f"{info['storage_bytes'] / 2 ** 20:.4g} MiB dense float32; "
                    f"{info['sparse_storage_bytes'] / 2 ** 20:.4g} MiB sparse "
                    f"({info['sparse_bricks']} bricks of 8^3 + apron); storage = auto "
                    f"would choose "
                    f"{'sparse' if info['sparse_storage_bytes'] <= 0.5 * info['storage_bytes'] else 'dense'}"),
        ("density min/max", f"{info['min']:.6g} / {info['max']:.6g}"),
        ("density mean", f"{info['mean']:.6g}"),
        ("max / mean", f"{info['max_over_mean']:.4g}"),
        ("majorant grid", f"{mres} cells; empty volume fraction "
                          f"{info['majorant_empty_fraction']:.4f}; mean cell bound / max "
                          f"{info['majorant_mean_over_max']:.4f}"),
    ]
    lines += _grid_lines(info)
    if info["nonfinite"] or info["negative"]:
        lines.append(("INVALID", f"{info['nonfinite']} non-finite value(s)"
                      + (", negative values" if info["negative"] else "")
                      + "; grid_medium will refuse this file"))
    return _aligned(lines)
