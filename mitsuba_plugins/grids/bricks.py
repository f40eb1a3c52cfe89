"""Sparse brick storage of a density grid, built from z-slabs (NumPy only).

The grid (``Z x Y x X x C`` voxels) is cut into bricks of :data:`BRICK`\\ :sup:`3` voxels.
A brick is *stored* when any value a lookup inside it can read is non-zero: its own
voxels or its apron, the one extra voxel layer on the high side of each axis that a
trilinear lookup near the brick's far faces blends in (clamped to the grid's last voxel
at the border, as ``gridvolume`` clamps). Stored bricks are ``SIDE^3 x C`` blocks
(``SIDE = BRICK + 1``) in one pool; slot 0 is a block of zeros that every empty brick's
entry of the indirection grid points to, so empty space costs one 32-bit entry per brick
and a lookup never branches. Each brick also keeps the per-channel maximum and minimum
of its block (the majorant grid is built from those, see :func:`cell_bounds`).

:class:`BrickBuilder` takes slabs of any thickness in z order and never holds more than
``SIDE`` z-slices of the dense grid, so loading a sparse grid costs about the pool, not
the box. This module imports nothing but NumPy: the OpenVDB worker (Debian's Python)
uses it too, to send only stored bricks through its pipe.
"""
from __future__ import annotations

import numpy as np

#: voxels per brick edge
BRICK = 8
#: stored voxels per brick edge (the brick plus its high-side apron)
SIDE = BRICK + 1


def brick_counts(shape) -> tuple:
    """Bricks per axis ``(Bz, By, Bx)`` of a ``(Z, Y, X, ...)`` grid."""
    return tuple(-(-int(n) // BRICK) for n in shape[:3])


class BrickBuilder:
    """Collects the stored bricks of a ``(Z, Y, X, C)`` grid fed as z-slabs in order."""

    def __init__(self, shape, keep_blocks: bool = True, bounds=None):
        """``keep_blocks`` false: count the stored bricks (and their extrema) only.
        ``bounds(blocks) -> (upper, lower)``: the per-voxel quantities whose extrema a
        brick keeps (default: the stored channels themselves)."""
        self.shape = tuple(int(s) for s in shape)
        self.keep_blocks = keep_blocks
        self.bounds = bounds
        z, y, x, c = self.shape
        self.counts = brick_counts(self.shape)
        bz, by, bx = self.counts
        #: slot of each brick in the pool (0: empty)
        self.index = np.zeros(self.counts, np.uint32)
        self.blocks = [np.zeros((1, SIDE, SIDE, SIDE, c), np.float32)]
        upper, lower = self._bounds(self.blocks[0])
        self.maxima = [upper.max(axis=(1, 2, 3))]     # per slot, per channel (or bound)
        self.minima = [lower.min(axis=(1, 2, 3))]
        self.stored = 1
        self._layers = []          # pending z-slices, each (Y, X, C)
        self._next_z = 0           # z of the next slice expected
        self._row = 0              # brick row (bz) to emit next

    # -- feeding -------------------------------------------------------------------
    def add(self, z0: int, slab: np.ndarray) -> None:
        """Feed ``slab`` ``(k, Y, X, C)`` starting at slice ``z0`` (in order)."""
        if z0 != self._next_z:
            raise ValueError(f"BrickBuilder: slab at z = {z0}, expected {self._next_z}")
        for layer in slab:
            self._layers.append(layer)
        self._next_z += slab.shape[0]
        z = self.shape[0]
        while self._row < self.counts[0]:
            first = self._row * BRICK
            need = min(first + SIDE, z) - first      # slices of this row present in the grid
            if len(self._layers) < need:
                break
            self._emit_row(self._layers[:need])
            self._layers = self._layers[BRICK:]      # keep the apron slice for the next row
            self._row += 1

    def add_blocks(self, row: int, cols, blocks: np.ndarray) -> None:
        """Record already cut blocks ``(n, SIDE, SIDE, SIDE, C)`` of brick row ``row`` at
        ``cols`` = ``(by, bx)`` index arrays (the OpenVDB worker's output)."""
        n = blocks.shape[0]
        if not n:
            return
        self.index[row, cols[0], cols[1]] = np.arange(self.stored, self.stored + n,
                                                      dtype=np.uint32)
        if self.keep_blocks:
            self.blocks.append(blocks)
        upper, lower = self._bounds(blocks)
        self.maxima.append(upper.max(axis=(1, 2, 3)))
        self.minima.append(lower.min(axis=(1, 2, 3)))
        self.stored += n

    def _bounds(self, blocks):
        return (blocks, blocks) if self.bounds is None else self.bounds(blocks)

    def add_row(self, row: int, cols, blocks: np.ndarray) -> None:
        """Record brick row ``row`` cut elsewhere (in order; see :meth:`add_blocks`)."""
        if row != self._row or self._layers:
            raise ValueError(f"BrickBuilder: brick row {row}, expected {self._row}")
        self.add_blocks(row, cols, blocks)
        self._row += 1
        self._next_z = min(self._row * BRICK, self.shape[0])

    def _emit_row(self, layers: list) -> None:
        _, y, x, c = self.shape
        cols, blocks = cut_row(np.stack(layers), (y, x, c))
        self.add_blocks(self._row, cols, blocks)

    # -- results -------------------------------------------------------------------
    def finish_check(self) -> None:
        """Raise unless every z-slice was fed."""
        if self._row < self.counts[0]:
            raise ValueError(f"BrickBuilder: {self._next_z} of {self.shape[0]} z-slices fed")

    def finish(self):
        """``(index, pool, maxima, minima)``: pool ``(stored, SIDE, SIDE, SIDE, C)``."""
        self.finish_check()
        pool = np.concatenate(self.blocks) if len(self.blocks) > 1 else self.blocks[0]
        self.blocks = []
        return (self.index, pool, *self.extrema())

    def extrema(self) -> tuple:
        """``(maxima, minima)``: per slot (0: the empty block), per channel."""
        return np.concatenate(self.maxima), np.concatenate(self.minima)

    def pool_chunks(self):
        """The pool as the list of its chunks (in slot order), handed over once: a caller
        that uploads them one by one never holds a second copy of the pool."""
        blocks, self.blocks = self.blocks, []
        return blocks


def cut_row(layers: np.ndarray, yxc, bricks=None) -> tuple:
    """Stored bricks of one brick row: ``layers`` ``(k, Y, X, C)`` are the row's slices,
    ``k <= SIDE`` (fewer at the grid's end, where the last slice is repeated). Returns
    ``((by, bx), blocks)`` with blocks ``(n, SIDE, SIDE, SIDE, C)``.

    ``bricks = (by, bx)``: cut that many bricks of a tile of the row whose ``layers``
    hold their apron where the grid goes on (``Y = 8 by + 1``), or end with the grid
    (``Y <= 8 by``; the last voxel is repeated, as lookups clamp). Default: every brick
    of ``Y x X`` voxels, which end with the grid."""
    y, x, c = yxc
    k = layers.shape[0]
    by, bx = bricks if bricks is not None else (-(-y // BRICK), -(-x // BRICK))
    # clamp-extend to whole bricks plus the apron (edge values repeated, as lookups clamp)
    pad = ((0, SIDE - k), (0, by * BRICK + 1 - y), (0, bx * BRICK + 1 - x), (0, 0))
    if any(p[1] for p in pad):
        layers = np.pad(layers, pad, mode="edge")
    # any non-zero bit over the slices (an OR of the float bits: -0.0 counts, harmlessly)
    bits = np.bitwise_or.reduce(layers.view(np.uint32), axis=0)    # (Y', X', C)
    nonzero = bits[..., 0] != 0 if c == 1 else np.any(bits != 0, axis=2)
    s0, s1 = nonzero.strides
    windows = np.lib.stride_tricks.as_strided(
        nonzero, (by, bx, SIDE, SIDE), (BRICK * s0, BRICK * s1, s0, s1), writeable=False)
    rows, cols = np.nonzero(windows.any(axis=(2, 3)))
    if not rows.size:
        return (rows, cols), np.zeros((0, SIDE, SIDE, SIDE, c), np.float32)
    t0, t1, t2, t3 = layers.strides
    view = np.lib.stride_tricks.as_strided(
        layers, (by, bx, SIDE, SIDE, SIDE, c), (BRICK * t1, BRICK * t2, t0, t1, t2, t3),
        writeable=False)
    return (rows, cols), np.ascontiguousarray(view[rows, cols], dtype=np.float32)


def _cells_of_bricks(per_brick: np.ndarray, ranges, op) -> np.ndarray:
    """``op`` (max or min) over the bricks holding each cell's voxel ranges."""
    for axis, (lo, hi) in enumerate(ranges):
        lo_b = lo // BRICK
        hi_b = np.maximum((hi - 1) // BRICK, lo_b)
        per_brick = np.stack([op(per_brick.take(np.arange(a, b + 1), axis=axis), axis=axis)
                              for a, b in zip(lo_b, hi_b)], axis=axis)
    return per_brick


def cell_bounds(maxima: np.ndarray, minima: np.ndarray, index: np.ndarray, shape,
                ranges, weights, product: bool = False) -> tuple:
    """Majorant and minorant cells ``(Rz, Ry, Rx)`` from the bricks' block extrema.

    ``ranges``: per axis (z, y, x) the inclusive voxel ranges a lookup in each cell can
    read (:func:`mitsuba_plugins.grids.bounds.voxel_ranges`). A brick's block holds its
    voxels and the high-side apron, so the bricks ``lo // BRICK .. (hi - 1) // BRICK``
    hold every voxel in ``[lo, hi]``; their extrema bound the cell (looser than voxel-exact bounds by
    at most the rest of those bricks). Gray bound: ``max_c w_c max_c``, ``min_c w_c min_c``.
    ``product``: the extrema are factors of a product
    (:class:`mitsuba_plugins.grids.bounds.ProductMajorantBuilder`): each factor's cell
    extremum, multiplied, times the (one) weight.
    """
    w = np.asarray(weights, np.float32)
    if product:
        upper = np.prod([_cells_of_bricks(maxima[:, f][index], ranges, np.max)
                         for f in range(maxima.shape[1])], axis=0)
        lower = np.prod([_cells_of_bricks(minima[:, f][index], ranges, np.min)
                         for f in range(minima.shape[1])], axis=0)
        return upper * w.max(), lower * w.max()
    return (_cells_of_bricks((maxima * w).max(axis=1)[index], ranges, np.max),
            _cells_of_bricks((minima * w).min(axis=1)[index], ranges, np.min))


def densify(index: np.ndarray, pool: np.ndarray, shape) -> np.ndarray:
    """The dense ``(Z, Y, X, C)`` grid of a brick pool (tests, ``storage='dense'``)."""
    z, y, x, c = shape
    bz, by, bx = index.shape
    out = np.zeros((bz * BRICK, by * BRICK, bx * BRICK, c), np.float32)
    for (i, j, k) in zip(*np.nonzero(index)):
        out[i * BRICK:(i + 1) * BRICK, j * BRICK:(j + 1) * BRICK, k * BRICK:(k + 1) * BRICK] = \
            pool[index[i, j, k], :BRICK, :BRICK, :BRICK]
    return out[:z, :y, :x]
