"""Where a grid sits in the world: the transforms of ``grid_medium``'s grids.

A grid's *local* frame is the unit cube of its loaded box (voxel ``i`` of an axis of ``N``
centred at ``(i + 1/2) / N``, ``gridvolume``'s convention); ``to_local`` maps world points
there. This module composes those transforms from a file's placement (a ``.vdb``'s
index-to-world matrix, a ``.vol`` box) and ``to_world``, checks them, and reads back the
transform of a Mitsuba volume, which Mitsuba does not expose.
"""
from __future__ import annotations

import re

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins.params import PluginParameterError

#: smallest |det| of to_world's linear part relative to its largest entry cubed
SINGULAR_TOLERANCE = 1e-12


def vdb_to_world(header, to_world: mi.ScalarTransform4f) -> mi.ScalarTransform4f:
    """Unit cube of a .vdb grid's loaded box -> world (OpenVDB placement): the file's
    index-to-world transform, then ``to_world``; composed and inverted in double
    precision, float32 only at the end."""
    from mitsuba_plugins.grids.gridheader import grid_to_world
    matrix = np.array(to_world.matrix, dtype=np.float64) @ grid_to_world(header)
    return mi.ScalarTransform4f(dr.scalar.Matrix4f(matrix.astype(np.float32)),
                                dr.scalar.Matrix4f(np.linalg.inv(matrix).T.astype(np.float32)))


def grid_to_local(header, to_world: mi.ScalarTransform4f, use_grid_bbox: bool,
                  filename: str) -> mi.ScalarTransform4f:
    """World -> the unit cube of a grid file's loaded box: ``to_world`` after the file's
    own placement (a ``.vdb``'s index-to-world transform; with ``use_grid_bbox`` a
    ``.vol`` header's bounding box)."""
    if header.index_to_world is not None:
        to_world = vdb_to_world(header, to_world)
    to_local = to_world.inverse()
    if use_grid_bbox:
        if header.bbox is None:
            raise PluginParameterError(
                f"grid_medium: parameter 'use_grid_bbox' needs a .vol file (with a "
                f"bounding box in its header); '{filename}' has none")
        lo, hi = (np.asarray(v, dtype=np.float32) for v in header.bbox)
        to_local = mi.ScalarTransform4f().scale(1.0 / (hi - lo)).translate(-lo) @ to_local
    return to_local


def check_invertible(value) -> None:
    """Refuse a ``to_world`` that is singular (a zero scale makes the medium vanish) or
    holds non-finite numbers."""
    matrix = np.array(value.matrix, dtype=np.float64)
    linear = matrix[:3, :3]
    det = float(np.linalg.det(linear)) if np.all(np.isfinite(matrix)) else float("nan")
    size = float(np.max(np.abs(linear))) if np.all(np.isfinite(linear)) else 0.0
    if not (np.isfinite(det) and abs(det) > SINGULAR_TOLERANCE * size ** 3 and size > 0):
        raise PluginParameterError(
            f"grid_medium: parameter 'to_world' is singular or not finite (determinant of "
            f"its 3x3 part {det:g}); allowed: an invertible transform (no zero scale)")


def world_linear(to_local) -> np.ndarray:
    """The 3x3 linear part of a grid's local -> world map (columns: the world images of
    the local unit axes)."""
    return np.array(to_local.inverse().matrix, dtype=np.float64)[:3, :3]


def transform(value) -> mi.ScalarTransform4f:
    """A Properties transform (double precision) as a float transform."""
    return mi.ScalarTransform4f(dr.scalar.Matrix4f(value.matrix),
                                dr.scalar.Matrix4f(value.inverse_transpose))


def world_bbox(to_local: mi.ScalarTransform4f) -> mi.ScalarBoundingBox3f:
    to_world = to_local.inverse()
    bbox = mi.ScalarBoundingBox3f()
    for corner in range(8):
        bbox.expand(to_world @ mi.ScalarPoint3f(corner & 1, (corner >> 1) & 1, corner >> 2))
    return bbox


def bbox_to_local(bbox) -> mi.ScalarTransform4f:
    lo = np.array(bbox.min, dtype=np.float32)
    extent = np.maximum(np.array(bbox.max, dtype=np.float32) - lo, 1e-30)
    return mi.ScalarTransform4f().scale(1.0 / extent).translate(-lo)


_MATRIX = re.compile(r"to_local = Transform\[\s*matrix=\[(.*?)\]\],", re.S)


def volume_grid(volume: mi.Volume, need_transform: bool = True):
    """``(data (Z, Y, X, C) numpy or None, to_local)`` of a Mitsuba volume.

    Only grid volumes expose data. Mitsuba does not expose a volume's transform, so it is
    read back from ``to_string()`` (6 significant digits; the majorant cells get a
    matching margin), and checked against the volume's bounding box.
    """
    params = mi.traverse(volume)
    if "data" not in params:
        return None, None
    data = np.asarray(params["data"].numpy(), dtype=np.float32)
    if data.ndim == 3:
        data = data[..., None]
    if not need_transform:
        return data, None
    match = _MATRIX.search(str(volume))
    to_local = None
    if match:
        rows = re.findall(r"\[([^\[\]]*)\]", match.group(1) + "]")
        try:
            matrix = np.array([[float(v) for v in r.split(",")] for r in rows], np.float32)
            to_local = mi.ScalarTransform4f(matrix) if matrix.shape == (4, 4) else None
        except ValueError:
            to_local = None
    bbox = volume.bbox()
    if to_local is not None:
        ours = world_bbox(to_local)
        size = float(np.max(np.abs(np.array(bbox.max) - np.array(bbox.min))))
        err = max(float(np.max(np.abs(np.array(ours.min) - np.array(bbox.min)))),
                  float(np.max(np.abs(np.array(ours.max) - np.array(bbox.max)))))
        if not err <= 1e-4 * max(size, 1.0):
            to_local = None
    if to_local is None:
        # Unreadable transform: one cell over the bounding box, still a valid bound.
        return None, None
    return data, to_local
