"""Lookups in sparse brick storage (:mod:`mitsuba_plugins.grids.bricks`) on the device.

Same convention as a clamped ``mi.Texture3f`` over the grid's unit cube: voxel ``i`` of
an axis of ``N`` voxels has its centre at ``(i + 1/2) / N``; trilinear lookups blend the
two voxels around ``x N - 1/2`` (clamped to ``[0, N - 1]``), nearest lookups read voxel
``floor(x N)`` (clamped). One gather reads the brick's pool slot from the indirection
grid; the voxels come from that one block (the apron holds the high-side neighbours), so
a trilinear lookup costs 1 + 8 gathers whatever the brick.

Editing and differentiating stored values (:meth:`SparseGrid.bricks`,
:meth:`SparseGrid.synchronize`): the pool is exposed as a tensor ``(stored, SIDE, SIDE,
SIDE, C)``; a voxel has one *owning* copy, in its own brick's ``BRICK^3`` interior (or,
for a voxel of a brick not stored, in the apron of a stored neighbour); other apron copies
and the clamp padding beyond the grid are copies that lookups read. After an edit
every copy is re-read from its owner by one gather, so gradients of lookups that read a
copy land on the owner (the copies' entries of the exposed tensor get none and their
values are ignored), and slot 0 stays zeros. Which bricks exist never changes: a voxel
that no stored brick holds stays 0 and has no gradient (a lookup addressed to an empty
brick reads slot 0).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_plugins.grids.bricks import BRICK, SIDE

#: pool elements moved to the device per scatter while loading
UPLOAD_CHUNK = 1 << 22


class SparseGrid:
    """Indirection grid + brick pool of a ``(Z, Y, X, C)`` grid, any C (1, 3; 4 for
    upsampled RGB in spectral variants)."""

    def __init__(self, shape, index: np.ndarray, chunks: list, stored: int):
        self.shape = tuple(int(s) for s in shape)
        self.channels = self.shape[3]
        self.counts = tuple(int(n) for n in index.shape)          # (Bz, By, Bx)
        self.stored = int(stored)
        self.index = mi.UInt32(index.ravel())
        block = SIDE ** 3 * self.channels
        self.pool = dr.zeros(mi.Float, self.stored * block)
        start = 0
        while chunks:                       # upload and free chunk by chunk
            values = chunks.pop(0).reshape(-1)
            for s in range(0, values.size, UPLOAD_CHUNK):
                part = values[s:s + UPLOAD_CHUNK]
                dr.scatter(self.pool, mi.Float(part),
                           dr.arange(mi.UInt32, start + s, start + s + part.size))
                dr.eval(self.pool)
            start += values.size
            del values
        if start != self.stored * block:
            raise ValueError(f"SparseGrid: pool has {start} values, expected "
                             f"{self.stored * block}")
        z, y, x = self.shape[:3]
        self._size_i = (x, y, z)
        dr.make_opaque(self.index, self.pool)
        self.index_host = index        #: the indirection grid (Bz, By, Bx) on the host
        self._tensor = None

    # -- editing ----------------------------------------------------------------------
    def bricks(self) -> mi.TensorXf:
        """The pool as a tensor ``(stored, SIDE, SIDE, SIDE, C)`` (slot 0: the empty
        block), for ``mi.traverse``; made once, sharing the pool's storage."""
        if self._tensor is None:
            self._tensor = mi.TensorXf(self.pool, shape=(self.stored, SIDE, SIDE, SIDE,
                                                         self.channels))
        return self._tensor

    @property
    def exposed(self) -> bool:
        """Whether :meth:`bricks` handed the pool out (to ``mi.traverse``)."""
        return self._tensor is not None

    def synchronize(self) -> None:
        """Re-derive the pool from the owning copies of the exposed tensor (after an edit
        through ``mi.traverse``; differentiable: one gather)."""
        tensor = self.bricks()
        expected = (self.stored, SIDE, SIDE, SIDE, self.channels)
        if tuple(tensor.shape) != expected:
            raise ValueError(f"changed shape from {expected} to {tuple(tensor.shape)}")
        source, owner = self._owners()
        self.pool = dr.gather(mi.Float, tensor.array, source, owner)
        dr.make_opaque(self.pool)

    def _owners(self):
        """For every pool element: the element of its voxel's owning copy, and whether the
        voxel has one (False: slot 0, read as 0). The owner is the copy in the voxel's own
        brick when that is stored, else (a voxel of an empty brick that a neighbour's
        apron holds) the apron copy of the first stored brick among the voxel's low
        neighbours, x first."""
        c, block = self.channels, SIDE ** 3
        e = dr.arange(mi.UInt32, self.stored * block * c)
        v = e // c
        slot, offset = v // block, v % block
        local = mi.Vector3i(offset % SIDE, (offset // SIDE) % SIDE, offset // (SIDE * SIDE))
        coords = self._slot_bricks()
        brick = mi.Vector3i(*(dr.gather(mi.Int32, mi.Int32(coords[:, k]), slot)
                              for k in (2, 1, 0)))
        voxel = dr.clip(brick * BRICK + local, 0, mi.Vector3i(*self._size_i) - 1)
        home = voxel // BRICK
        source, found = dr.zeros(mi.UInt32, dr.width(e)), slot > 0
        owned = mi.Bool(False)
        for dz, dy, dx in ((0, 0, 0), (0, 0, 1), (0, 1, 0), (0, 1, 1), (1, 0, 0), (1, 0, 1),
                           (1, 1, 0), (1, 1, 1)):
            b = home - mi.Vector3i(dx, dy, dz)
            inner = voxel - b * BRICK               # 0..8: the apron is 8
            ok = found & ~owned & dr.all(b >= 0) & dr.all(inner <= BRICK)
            entry = mi.UInt32((b.z * self.counts[1] + b.y) * self.counts[2] + b.x)
            b_slot = dr.gather(mi.UInt32, self.index, entry, ok)
            ok &= b_slot > 0
            element = (b_slot * block + mi.UInt32((inner.z * SIDE + inner.y) * SIDE
                                                  + inner.x)) * c + e % c
            source = dr.select(ok, element, source)
            owned |= ok
        return source, owned

    def densify(self, values) -> np.ndarray:
        """The ``(Z, Y, X, C)`` grid of ``values`` laid out as :meth:`bricks` (e.g. the
        gradient of the bricks), read at each voxel's owning copy; 0 where a voxel has
        none."""
        source, owned = (np.asarray(a) for a in self._owners())
        mine = np.nonzero(owned & (source == np.arange(source.size)))[0]
        c, block = self.channels, SIDE ** 3
        v = mine // c
        offset = v % block
        local = np.stack([offset // (SIDE * SIDE), (offset // SIDE) % SIDE, offset % SIDE], 1)
        voxel = self._slot_bricks()[v // block] * BRICK + local
        out = np.zeros(self.shape, np.float32)
        out[voxel[:, 0], voxel[:, 1], voxel[:, 2], mine % c] = \
            np.asarray(values, np.float32).reshape(-1)[mine]
        return out

    def _slot_bricks(self) -> np.ndarray:
        """Brick coordinates ``(z, y, x)`` of every pool slot (slot 0: zeros), from the
        indirection grid."""
        bz, by, bx = np.nonzero(self.index_host)
        coords = np.zeros((self.stored, 3), np.int32)
        coords[self.index_host[bz, by, bx]] = np.stack([bz, by, bx], axis=1)
        return coords

    def extrema(self) -> tuple:
        """``(maxima, minima)`` per slot and channel of the current pool (host)."""
        blocks = self.pool.numpy().reshape(self.stored, -1, self.channels)
        return blocks.max(axis=1), blocks.min(axis=1)

    @property
    def nbytes(self) -> int:
        """Device bytes of the indirection grid and the pool."""
        return 4 * (int(np.prod(self.counts)) + self.stored * SIDE ** 3 * self.channels)

    def _slot_base(self, voxel: mi.Vector3i, active) -> mi.UInt32:
        """Voxel index in the pool (slot x SIDE^3 + offset in the block); times C for
        the element (``dr.gather`` of a ``Color3f`` scales by 3 itself)."""
        bx, by = self.counts[2], self.counts[1]
        brick = voxel >> 3 if BRICK == 8 else voxel // BRICK
        local = voxel - brick * BRICK
        entry = mi.UInt32((brick.z * by + brick.y) * bx + brick.x)
        slot = dr.gather(mi.UInt32, self.index, entry, active)
        offset = mi.UInt32((local.z * SIDE + local.y) * SIDE + local.x)
        return slot * (SIDE ** 3) + offset

    def _read(self, element: mi.UInt32, active):
        """The voxel at pool element ``element``: ``Float``, ``Color3f``, or for another
        channel count (4: an upsampled RGB voxel, mitsuba_plugins.grids.spectra) a list."""
        if self.channels == 1:
            return dr.gather(mi.Float, self.pool, element, active)
        if self.channels == 3:
            return dr.gather(mi.Color3f, self.pool, element, active)
        return [dr.gather(mi.Float, self.pool, element * self.channels + k, active)
                for k in range(self.channels)]

    def _corner(self, p: mi.Point3f, active):
        """Pool element of the low corner of the trilinear cell around local ``p``, and
        the position ``f`` in that cell."""
        size = mi.Vector3f(*self._size_i)
        q = dr.clip(p * size - 0.5, 0.0, size - 1.0)
        base_f = dr.floor(q)
        return self._slot_base(mi.Vector3i(base_f), active), q - base_f

    def fetch(self, p: mi.Point3f, active=True):
        """The 8 voxels a trilinear lookup at ``p`` blends (x fastest, then y, z, as
        ``Texture3f.eval_fetch``) and the position ``f`` between them."""
        base, f = self._corner(p, active)
        corners = [self._read(base + (dz * SIDE + dy) * SIDE + dx, active)
                   for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)]
        return corners, f

    def eval(self, p: mi.Point3f, trilinear: bool, active=True):
        """Value at local point ``p`` (unit cube): ``mi.Float`` or ``mi.Color3f``."""
        if not trilinear:
            size = mi.Vector3f(*self._size_i)
            voxel = mi.Vector3i(dr.clip(dr.floor(p * size), 0.0, size - 1.0))
            return self._read(self._slot_base(voxel, active), active)
        base, f = self._corner(p, active)
        g = 1.0 - f
        result = None
        for dz in (0, 1):
            wz = f.z if dz else g.z
            for dy in (0, 1):
                wy = f.y if dy else g.y
                for dx in (0, 1):
                    wx = f.x if dx else g.x
                    step = (dz * SIDE + dy) * SIDE + dx
                    value = self._read(base + step, active)
                    term = value * (wz * wy * wx)
                    result = term if result is None else result + term
        return result
