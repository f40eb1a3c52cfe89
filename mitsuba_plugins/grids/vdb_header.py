"""The list of grids in an OpenVDB file, read from its header without OpenVDB.

OpenVDB's Python module cannot list a file that holds a grid of a type it was not built
for (Debian's lists nothing once any grid is ``double``, ``int32``, ``vec3d`` or a
mask), and its warnings go to standard output. The grid descriptors at the head of a
``.vdb`` are simple, so they are read here (OpenVDB's ``Archive::readHeader`` and
``GridDescriptor::read``, file format versions 211 and later):

* int64 magic ``0x56444220``, uint32 format version, uint32 library major and minor,
  char "has grid offsets", (versions 220-221: uint32 compression), 36 bytes of UUID;
* the file's metadata: uint32 count, then per entry name, type name (uint32 length +
  bytes each) and value (uint32 size + bytes);
* int32 grid count, then per grid: unique name, tree type (``Tree_float_5_4_3``, with
  ``_HalfFloat`` when stored as half), instance parent (versions >= 216), and int64
  grid, block and end offsets; the next descriptor starts at the end offset.

Several grids of one name are told apart as OpenVDB does: their unique names carry a
suffix after the separator ``\\x1e`` (``density``, ``density\\x1e1``, ...), which OpenVDB's
readers accept written as ``density[1]``. That form is a grid's *address* here when its
name is not unique.
"""
from __future__ import annotations

import dataclasses
import os
import struct

MAGIC = 0x56444220
#: first format version with the header read here (library version in the header)
MIN_VERSION = 211
#: separator of a unique name's suffix (OpenVDB's GridDescriptor::SEP)
SEPARATOR = "\x1e"
HALF_SUFFIX = "_HalfFloat"
#: longest name or metadata value accepted while reading (a corrupt length is refused)
MAX_STRING = 1 << 20
MAX_GRIDS = 1 << 16


class VdbHeaderError(ValueError):
    """The file is not a readable OpenVDB file (one line, without the file name)."""


@dataclasses.dataclass(frozen=True)
class GridEntry:
    index: int          # position in the file, from 0
    name: str           # the grid's name
    address: str        # what selects it: the name if unique, else ``name[k]``
    value_type: str     # float, half, vec3s, double, int32, bool, mask, ...
    tree_type: str      # OpenVDB's tree type name, e.g. Tree_float_5_4_3


class _Reader:
    def __init__(self, f, size: int):
        self.f, self.size = f, size

    def raw(self, n: int) -> bytes:
        data = self.f.read(n)
        if len(data) != n:
            raise VdbHeaderError(f"header cut short at byte {self.f.tell()} of {self.size}")
        return data

    def unpack(self, fmt: str):
        return struct.unpack("<" + fmt, self.raw(struct.calcsize("<" + fmt)))[0]

    def string(self) -> str:
        n = self.unpack("I")
        if n > MAX_STRING:
            raise VdbHeaderError(f"a name of {n} bytes at byte {self.f.tell() - 4}")
        return self.raw(n).decode("utf-8", errors="replace")

    def seek(self, offset: int) -> None:
        if not 0 <= offset <= self.size:
            raise VdbHeaderError(f"truncated: a grid ends at byte {offset}, past the end "
                                 f"of the file's {self.size} bytes" if offset > self.size else
                                 f"a grid offset {offset} outside the file's {self.size} bytes")
        self.f.seek(offset)


def value_type(tree_type: str) -> str:
    """``Tree_float_5_4_3_HalfFloat`` -> ``half``; ``Tree_vec3s_5_4_3`` -> ``vec3s``."""
    if tree_type.endswith(HALF_SUFFIX):
        return "half"
    parts = tree_type.split("_")
    return parts[1] if len(parts) > 2 and parts[0] == "Tree" else tree_type


def read_grid_list(path) -> list:
    """Every grid of the ``.vdb`` at ``path``, in file order, as :class:`GridEntry`;
    :class:`VdbHeaderError` when the header cannot be read."""
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        r = _Reader(f, size)
        head = f.read(8)
        if len(head) != 8 or struct.unpack("<q", head)[0] != MAGIC:
            raise VdbHeaderError("not an OpenVDB file (no VDB magic number)")
        version = r.unpack("I")
        if version < MIN_VERSION:
            raise VdbHeaderError(f"file format version {version}; allowed: >= {MIN_VERSION}")
        r.unpack("I"), r.unpack("I")                    # library version
        if not r.unpack("B"):
            raise VdbHeaderError("no grid offsets (written by OpenVDB before 2.0)")
        if 220 <= version < 222:
            r.unpack("I")                                # file-wide compression
        r.raw(36)                                        # UUID
        for _ in range(r.unpack("I")):                   # file metadata
            r.string(), r.string()
            n = r.unpack("I")
            if n > MAX_STRING:
                raise VdbHeaderError(f"a metadata value of {n} bytes")
            r.raw(n)
        count = r.unpack("i")
        if not 0 <= count <= MAX_GRIDS:
            raise VdbHeaderError(f"grid count {count}")
        unique, trees = [], []
        for _ in range(count):
            unique.append(r.string())
            trees.append(r.string())
            if version >= 216:
                r.string()                               # instance parent
            _, _, end = r.unpack("q"), r.unpack("q"), r.unpack("q")
            r.seek(end)
    names = [u.split(SEPARATOR, 1)[0] for u in unique]
    entries = []
    for i, (u, name, tree) in enumerate(zip(unique, names, trees)):
        if names.count(name) > 1:
            suffix = u.split(SEPARATOR, 1)[1] if SEPARATOR in u else "0"
            address = f"{name}[{suffix}]"
        else:
            address = name
        entries.append(GridEntry(i, name, address, value_type(tree), tree))
    return entries


def select(entries: list, grid: str):
    """The entry ``grid`` addresses (a unique name, or ``name[k]``); raises
    :class:`LookupError` naming the choices when it is missing or ambiguous."""
    by_address = [e for e in entries if e.address == grid]
    if by_address:
        return by_address[0]
    same = [e for e in entries if e.name == grid]
    if len(same) > 1:
        choices = ", ".join(f"'{e.address}'" for e in same)
        raise LookupError(f"{len(same)} grids are named {grid!r}; choose one by its "
                          f"address: {choices}")
    names = ", ".join(repr(e.address) for e in entries) or "none"
    raise LookupError(f"no grid named {grid!r}; the file holds: {names}")
