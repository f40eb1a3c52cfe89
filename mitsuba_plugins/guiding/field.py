"""A guiding field: where light comes from, learnt while rendering (docs/method.md
section 13).

Space: a regular grid of ``R^3`` cells over a box (the bounds of the scene's media).
Direction: per cell, one von Mises-Fisher lobe mixed with the uniform distribution,
``g(w) = (1 - u) vMF(w; mu, kappa) + u / (4 pi)``, fitted by moments: the records' sum
``W`` of incident radiance and their sum ``V`` of radiance times direction give the
lobe's axis ``mu = V / |V|`` and mean cosine ``r = |V| / W``, hence ``kappa`` (Banerjee
et al. 2005's approximation ``kappa = r (3 - r^2) / (1 - r^2)``). That is the first two
moments of the incident radiance, what the diffusion (P1) approximation keeps of it in a
dense medium.

Why this and not a histogram per cell: a histogram of 32 to 128 bins was tried first
(equal-area bins, CDF inverted by binary search). Each bin's estimate is noisy, and the
noise becomes a per-vertex weight that multiplies over the tens of vertices of a dense
medium: resampling by it raised the variance of a dense ball (depth 64) 2.5-5.6x. Four
numbers per cell are estimated from all of the cell's records at once, and where the
light has no direction ``r`` is small and the lobe is flat. The tables are arrays that
the kernels gather from, so a field that learns never recompiles a kernel.

Learning: each recorded vertex adds ``Li(w) / p(w)`` (the radiance the path gathered
after the vertex along the sampled direction ``w``, over the density that drew it) to
``W`` and that times ``w`` to ``V``: unbiased estimates of ``int Li`` and ``int Li w``.
Cells with fewer than ``MIN_RECORDS`` records stay uniform. The mean cosine counts only
the part of ``|V|`` that the records resolve beyond their own noise
(:meth:`GuidingField.update`).

Surfaces (``path_rr``) use :class:`HistogramField` instead: a surface path's weights do
not compound over tens of vertices, so there the histogram's resolution is worth its noise.

Every pdf is exact: :meth:`GuidingField.pdf` is the density of :meth:`GuidingField.sample`
(tests/guiding/test_guiding.py checks both classes against histograms of their own samples).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

#: default cells per axis
RESOLUTION = 8
#: share of the uniform distribution in every cell's lobe: it bounds a resampled
#: vertex's weight (the lobe's peak over its floor); chosen on the tuning set (64x64, 12
#: renders of 64 spp, relMSE over unguided volpath_delta's): 0.2 / 0.35 / 0.5 gave lamp
#: ball 0.218 / 0.208 / 0.223, gap room 0.449 / 0.452 / 0.459, dense ball 0.90 / 0.84 /
#: 0.90 (its worst render 1.41 / 1.11 / 1.03)
UNIFORM = 0.35
#: the same for :class:`HistogramField`'s bins (surfaces, tuned with them)
BIN_UNIFORM = 0.2
#: records a cell needs before it has a lobe
MIN_RECORDS = 64
#: largest mean cosine a lobe is fitted to (kappa about 10)
MAX_COSINE = 0.9
#: below this concentration a lobe is sampled and evaluated as uniform
FLAT = 1e-3
#: largest memory the tables of a field may take (bytes): 64 MiB
MAX_BYTES = 64 << 20
#: learnt next-event estimation (``path_rr``'s ``guiding_nee``, :meth:`GuidingField.update`):
#: the lowest probability of sampling an emitter at a vertex, which keeps the estimate
#: unbiased where the records saw no direct light by chance
NEE_MIN = 0.05
#: ... and the share of a path's time that its emitter samples take, ``rho`` of
#: :meth:`GuidingField.nee_probabilities` (measured: 0.22-0.38 of a plain ``path_rr``
#: pass on the door room, 128x128, 64 spp, with and without them)
NEE_SHARE = 0.3
#: the emitter samples' statistics are kept per cell and per side a surface faces (the
#: dominant axis of its normal, turned toward the incident direction, and its sign): a
#: cell that holds a wall's two sides, or a floor and a ceiling, sees direct light on one
#: and none on the other
NEE_SIDES = 6


def field_bytes(resolution: int, bins: int = 0) -> int:
    """Bytes of a field of ``resolution^3`` cells: per cell a lobe (4 floats), its fluence,
    :data:`ACC_STRIDE` accumulators (5 sums, a record count, the squared values' sum, a
    spare), 4 sums of the paths' light, and per side (:data:`NEE_SIDES`) an emitter
    sample's probability and its 2 accumulators on the device, 6 sums and a count, and
    per side the emitter samples' 2 sums, on the host (:data:`CELL_BYTES`); with ``bins``
    (:class:`HistogramField`) ``bins^2`` bins of 4 words on the device (probability,
    cumulative, guide table, accumulator) and a double on the host, and its portals: 8
    floats per cell and, while a training pass keeps their records, up to
    :data:`PORTAL_ROWS` rows of 16 floats per cell (:data:`PORTAL_BUFFER` rows at most)
    on the device and :data:`PORTAL_KEPT` records of 9 floats on the host.
    """
    cells = resolution ** 3
    portals = 0 if not bins else \
        cells * 8 * 4 + min(cells * PORTAL_ROWS, PORTAL_BUFFER) * PORTAL_STRIDE * 4 + \
        PORTAL_KEPT * 9 * 4
    return cells * (CELL_BYTES + bins * bins * (4 * 4 + 8)) + portals


def check_memory(resolution: int, bins: int = 0) -> None:
    """Refuse parameters whose field would pass :data:`MAX_BYTES` (called when a plugin
    loads, and by every field)."""
    total = field_bytes(resolution, bins)
    if total > MAX_BYTES:
        raise ValueError(
            f"guiding_resolution = {resolution} and guiding_bins = {bins}: the field "
            f"would take {total / 2**20:.0f} MiB; allowed: at most {MAX_BYTES >> 20} MiB "
            "(field_bytes in mitsuba_plugins/guiding/field.py)")


def grid_box(bbox) -> tuple:
    """``(lo, 1 / size)`` of a grid over ``bbox`` (padded by 0.1%), as Python floats: an
    mi.Point3f made from a NumPy array inside a symbolic loop read garbage (measured:
    cells 26, 4, 0 where 346, 292, 165)."""
    lo, hi = np.array(bbox.min, np.float64), np.array(bbox.max, np.float64)
    pad = np.maximum((hi - lo) * 1e-3, 1e-4)
    return [float(v) for v in lo - pad], [float(v) for v in 1.0 / (hi - lo + 2 * pad)]


def grid_cell(lo, inv_size, r: int, p: mi.Point3f) -> mi.UInt32:
    """The cell of an ``r^3`` grid over the box ``(lo, 1 / size)`` holding ``p`` (clamped)."""
    return cell_index((p - mi.Point3f(*lo)) * mi.Vector3f(*inv_size) * r, r)


def cell_index(x: mi.Vector3f, r: int) -> mi.UInt32:
    """The cell of an ``r^3`` grid at ``x`` in cell units (clamped to the grid)."""
    i = mi.Vector3i(dr.clip(mi.Vector3i(dr.floor(x)), 0, r - 1))
    return mi.UInt32((i.z * r + i.y) * r + i.x)


#: floats per cell of the records' accumulators, one array (``GuidingField.acc``): W, Vx,
#: Vy, Vz, N, the records' count, the sum of the records' squared values (the noise of
#: V, :meth:`GuidingField.update`) and one spare (what the paths whose first vertex lies
#: in a cell gathered beyond its direct light and in all has an array of its own,
#: :meth:`GuidingField.record_flow`). A power of two, so that Dr.Jit's LLVM
#: backend adds a record with one packet scatter (``JitFlag.PacketOps``) instead of one
#: scatter per sum (with the light grid's pairs, ``distance.LightGrid.acc``: the camera
#: inside the cloud's training passes of 16 and 32 spp at 128x128 took 0.25 and 0.50 s
#: against 0.29 and 0.58 s, its guided render of 256 spp 3.74-3.81 s against 3.93 s).
#: The count is a float: exact to 2^24 per pass and thread, and it only decides whether
#: a cell has :data:`MIN_RECORDS`.
ACC_STRIDE = 8
#: bytes per cell of a field without bins (:func:`field_bytes`)
CELL_BYTES = 4 * 4 + 4 + ACC_STRIDE * 4 + 4 * 4 + NEE_SIDES * (4 + 2 * 4 + 2 * 8) + \
    6 * 8 + 8


def packed(*values, stride: int = ACC_STRIDE) -> mi.ArrayXf:
    """``values`` (Floats or Python numbers) as one record of ``stride`` floats (a power
    of two), zero-padded, for a packet ``dr.scatter_reduce`` at a cell's index."""
    width = dr.width(next((v for v in values if isinstance(v, mi.Float)), mi.Float(0)))
    out = dr.zeros(mi.ArrayXf, (stride, width))
    for j, v in enumerate(values):
        out[j] = v
    return out


def concentration(r: np.ndarray) -> np.ndarray:
    """``kappa`` of a vMF lobe of mean cosine ``r`` (Banerjee et al. 2005)."""
    r = np.clip(r, 0.0, MAX_COSINE)
    return r * (3.0 - r * r) / (1.0 - r * r)


class GuidingField:
    """Spatial grid x one vMF lobe (plus a uniform share) per cell, over ``bbox`` (a
    ``mi.ScalarBoundingBox3f``)."""

    #: whether a lobe's mean cosine is fitted to the part of ``|V|`` its records resolve
    #: beyond their own noise (:meth:`update`); :class:`HistogramField` keeps the plain
    #: fit, since its lobes only say which cells are trained
    NOISE_AWARE = True

    def __init__(self, bbox, resolution: int = RESOLUTION):
        self.resolution = int(resolution)
        self.cells = self.resolution ** 3
        check_memory(self.resolution, getattr(self, "bins", 0))
        self.lo, self.inv_size = grid_box(bbox)
        self.sums = np.zeros((self.cells, 6), np.float64)        # W, Vx, Vy, Vz, N, S2
        self.records = np.zeros(self.cells, np.int64)
        # per cell and side (NEE_SIDES): the emitter samples' q x contribution^2 and their
        # count
        self.nee_sums = np.zeros((self.cells * NEE_SIDES, 2), np.float64)
        self.nee_per_path = 0.0
        # what the last pass's paths gathered beyond their first vertex's direct light,
        # in all, its square, and their count (record_flow)
        self.flow = np.zeros(4)
        self._upload(np.zeros((self.cells, 3)), np.zeros(self.cells))

    def memory(self) -> int:
        """Bytes of the device tables (lobes, accumulators) and the host sums."""
        return field_bytes(self.resolution)

    # -- tables ------------------------------------------------------------------------
    def _upload(self, mu: np.ndarray, kappa: np.ndarray, fluence=None, nee=None) -> None:
        # ``kappa``: 0 for the uniform distribution (no lobe, or one below FLAT); the
        # density's factor ``(1 - UNIFORM) kappa / (2 pi (1 - exp(-2 kappa)))`` is tabled
        # per cell, so that a lookup costs one exponential per direction
        k = np.where(kappa > 0, kappa, 1.0)
        norm = np.where(kappa > 0, k / (2 * math.pi * -np.expm1(-2.0 * k)), 1.0 / (4 * math.pi))
        self.mu = [mi.Float(mu[:, i].astype(np.float32)) for i in range(3)]
        self.kappa = mi.Float(kappa.astype(np.float32))
        self.norm = mi.Float(((1.0 - UNIFORM) * norm).astype(np.float32))
        self.fluence = mi.Float((np.zeros(self.cells) if fluence is None else fluence)
                                .astype(np.float32))
        self.nee = mi.Float((np.ones(self.cells * NEE_SIDES) if nee is None else nee)
                            .astype(np.float32))
        self.acc = dr.zeros(mi.Float, self.cells * ACC_STRIDE)     # record's accumulators
        self.acc_flow = dr.zeros(mi.Float, self.cells * 4)         # record_flow's sums
        self.acc_nee = dr.zeros(mi.Float, self.cells * NEE_SIDES * 2)  # record_nee's pairs
        dr.eval(*self.mu, self.kappa, self.norm, self.fluence, self.nee, self.acc,
                self.acc_flow, self.acc_nee)

    def update(self) -> int:
        """Fold the records of the last pass into the lobes (host side, between passes);
        returns how many cells have a lobe now.

        With :attr:`NOISE_AWARE`, the mean cosine is ``sqrt(max(|V|^2 - S2, 0)) / W``,
        ``S2`` the sum of the records' squared values: for independent records ``E|V|^2
        = |E V|^2 + sum Var(v_i)``, and ``S2`` estimates that sum (from above), so
        records of light without direction (a dense medium of albedo near 1, where the
        radiance is nearly isotropic) no longer fit a lobe to their own noise. Where
        light has a direction ``|V|^2`` is far above ``S2`` and the lobe is the same."""
        acc = np.array(self.acc, np.float64).reshape(self.cells, ACC_STRIDE)
        self.flow = np.array(self.acc_flow, np.float64).reshape(self.cells, 4).sum(axis=0)
        self.sums[:, :5] += acc[:, :5]
        self.sums[:, 5] += acc[:, 6]
        self.records += np.rint(acc[:, 5]).astype(np.int64)
        nee = np.array(self.acc_nee, np.float64).reshape(-1, 2)
        self.nee_sums += nee
        # emitter-sample vertices per path of the last pass (nee_probabilities)
        self.nee_per_path = nee[:, 1].sum() / max(self.flow[3], 1.0)
        W, V, N = self.sums[:, 0], self.sums[:, 1:4], self.sums[:, 4]
        length = np.linalg.norm(V, axis=1)
        resolved = np.sqrt(np.maximum(length * length - self.sums[:, 5], 0.0)) \
            if self.NOISE_AWARE else length
        known = (self.records >= MIN_RECORDS) & (W > 0) & np.isfinite(W) & (N > 0)
        fitted = known & (length > 0)
        mu = np.where(fitted[:, None], V / np.where(length > 0, length, 1.0)[:, None], 0.0)
        kappa = np.where(fitted, concentration(resolved / np.where(W > 0, W, 1.0)), 0.0)
        kappa = np.where(kappa < FLAT, 0.0, kappa)     # below FLAT: uniform, no lobe
        self._upload(mu, kappa, np.where(known, W / np.where(N > 0, N, 1.0), 0.0),
                     self.nee_probabilities())
        return int((kappa > 0).sum())

    def nee_probabilities(self) -> np.ndarray:
        """Per cell and side (:data:`NEE_SIDES`, :meth:`nee_index`), the probability
        ``q`` that a vertex samples an emitter (``path_rr``'s ``guiding_nee``), clamped to
        [:data:`NEE_MIN`, 1]: taking the sample with probability ``q`` and dividing it by
        ``q`` adds ``a (1 / q - 1)`` to a pixel's variance per sample, ``a`` the squared
        contributions (throughput included, each over its pixel's squared value, as
        relMSE weighs errors: :meth:`record_nee`) of the side's emitter samples per path, and
        saves ``(1 - q) n c`` of its time, ``n`` the side's vertices per path and ``c``
        one emitter sample's cost. The product of variance ``V`` and time ``T`` is least
        at ``q = sqrt(a T / (n c V))``. Here ``a / n`` is the side's mean squared
        contribution per vertex (``q`` times the square of what a sample added, over all
        its vertices, taken or not), ``T / c = n_all / rho`` with ``n_all`` every side's
        vertices per path and ``rho`` (:data:`NEE_SHARE`) the emitter samples' share of
        the time, and ``V`` the mean square of the paths' light over their pixels' (the
        last pass's). So a side whose samples bring a path's light keeps
        ``q = 1``, one whose samples find nothing (lights it cannot see) falls to
        ``NEE_MIN``. 1 where a side has fewer than :data:`MIN_RECORDS` vertices or the
        last pass found no light."""
        A_sum, count = self.nee_sums[:, 0], self.nee_sums[:, 1]
        paths, V = self.flow[3], self.flow[2] / max(self.flow[3], 1.0)
        if not (paths > 0 and V > 0 and np.isfinite(V)):
            return np.ones(len(count))
        per_path = self.nee_per_path
        A = A_sum / np.where(count > 0, count, 1.0)
        known = (count >= MIN_RECORDS) & np.isfinite(A)
        q = np.sqrt(np.maximum(A, 0.0) * per_path / (NEE_SHARE * V))
        return np.where(known, np.clip(q, NEE_MIN, 1.0), 1.0)

    # -- lookups (Dr.Jit, any variant) --------------------------------------------------
    def cell(self, p: mi.Point3f) -> mi.UInt32:
        """The cell holding ``p`` (clamped to the grid)."""
        return grid_cell(self.lo, self.inv_size, self.resolution, p)

    def lobe(self, cell: mi.UInt32, active=True):
        """``(mu, kappa)`` of ``cell``."""
        mu = mi.Vector3f(*[dr.gather(mi.Float, m, cell, active) for m in self.mu])
        return mu, dr.gather(mi.Float, self.kappa, cell, active)

    def trained(self, cell: mi.UInt32, active=True) -> mi.Bool:
        """Whether ``cell`` has learnt a distribution (enough records, a lobe)."""
        return dr.gather(mi.Float, self.kappa, cell, active) > 0

    def pdf(self, cell: mi.UInt32, d: mi.Vector3f, active=True) -> mi.Float:
        """Solid-angle density of :meth:`sample` in ``cell`` at the unit direction ``d``."""
        return self.lookup(cell, active)(d)

    def lookup(self, cell: mi.UInt32, active=True):
        """``cell``'s density as a function of the unit direction: its tables gathered
        once, for the several directions a vertex weighs."""
        mu, kappa = self.lobe(cell, active)
        norm = dr.gather(mi.Float, self.norm, cell, active)
        return lambda d: dr.fma(norm, dr.exp(kappa * (dr.dot(mu, d) - 1.0)),
                                UNIFORM / (4 * math.pi))

    def sample(self, cell: mi.UInt32, u: mi.Point2f, active=True) -> mi.Vector3f:
        """A direction from ``cell``'s mixture: ``u.x`` chooses uniform or lobe and is
        reused for the cosine, ``u.y`` gives the angle around the axis."""
        mu, kappa = self.lobe(cell, active)
        uniform = u.x < UNIFORM
        x = dr.select(uniform, u.x / UNIFORM, (u.x - UNIFORM) / (1.0 - UNIFORM))
        flat = uniform | (kappa < FLAT)
        k = dr.select(kappa < FLAT, 1.0, kappa)
        cos = dr.select(flat, 1.0 - 2.0 * x,
                        1.0 + dr.log(dr.maximum(x + (1.0 - x) * dr.exp(-2.0 * k), 1e-30)) / k)
        cos = dr.clip(cos, -1.0, 1.0)
        axis = dr.select(flat, mi.Vector3f(0, 0, 1), mu)
        frame = mi.Frame3f(axis)
        s = dr.safe_sqrt(1.0 - cos * cos)
        phi = 2 * math.pi * u.y
        return frame.to_world(mi.Vector3f(s * dr.cos(phi), s * dr.sin(phi), cos))

    @staticmethod
    def nee_index(cell: mi.UInt32, n: mi.Vector3f) -> mi.UInt32:
        """The index of ``cell``'s side that a surface of normal ``n`` (turned toward
        the incident direction) faces: ``NEE_SIDES cell + 2 axis + (n[axis] < 0)``, ``axis``
        that of ``n``'s largest component."""
        a = dr.abs(n)
        axis = dr.select((a.x >= a.y) & (a.x >= a.z), 0, dr.select(a.y >= a.z, 1, 2))
        comp = dr.select(axis == 0, n.x, dr.select(axis == 1, n.y, n.z))
        return cell * NEE_SIDES + mi.UInt32(axis) * 2 + dr.select(comp < 0, 1, 0)

    def nee_probability(self, index: mi.UInt32, active=True) -> mi.Float:
        """The probability that a vertex at ``index`` (:meth:`nee_index`) samples an
        emitter (:meth:`nee_probabilities`)."""
        return dr.gather(mi.Float, self.nee, index, active)

    def record_nee(self, index: mi.UInt32, value: mi.Float, q: mi.Float, active,
                   weight=1.0) -> None:
        """Add a vertex's emitter sample to the pair of :attr:`acc_nee` at ``index``
        (:meth:`nee_index`): ``weight q value^2`` and a count of 1. ``value``: what the
        sample added to the path's light, throughput included (channels averaged; 0
        where the vertex did not sample an emitter), taken with probability ``q``: ``q
        value^2`` estimates the square of what it adds when taken every time;
        ``weight``: one over the square of the path's pixel's value as the passes so far
        estimate it (``guided_render.pixel_weights``), so that squares of light count
        relative to their pixels, as relMSE counts errors."""
        ok = active & dr.isfinite(value)
        dr.scatter_reduce(dr.ReduceOp.Add, self.acc_nee,
                          packed(weight * q * value * value, 1.0, stride=2), index, ok)

    def radiance(self, cell: mi.UInt32, active=True) -> mi.Float:
        """The learnt fluence of ``cell`` (mean over its vertices of ``int Li``, channels
        averaged); 0 where the cell has too few records to tell."""
        return dr.gather(mi.Float, self.fluence, cell, active)

    def record(self, cell: mi.UInt32, d: mi.Vector3f, value: mi.Float, active,
               weight=1.0) -> None:
        """Add ``value`` (``Li / p`` of one vertex along ``d``, or ``f cos Li / p`` at a
        surface, times ``weight``: the vertices the record stands for) to ``cell``'s
        sums, and ``weight`` to its count."""
        ok = active & dr.isfinite(value) & (value >= 0)
        dr.scatter_reduce(dr.ReduceOp.Add, self.acc, packed(
            value, value * d.x, value * d.y, value * d.z, weight, 1.0, value * value), cell, ok)

    def record_flow(self, cell: mi.UInt32, after: mi.Float, total: mi.Float,
                    active, weight=1.0) -> None:
        """Add what a path gathered beyond its first recorded vertex's direct light (that
        vertex lies in ``cell``), in all, its square times ``weight`` and a count of 1 to
        ``cell``'s sums of :attr:`acc_flow` (:attr:`flow`, summed over cells by
        :meth:`update`)."""
        ok = active & dr.isfinite(total) & dr.isfinite(after)
        dr.scatter_reduce(dr.ReduceOp.Add, self.acc_flow,
                          packed(after, total, weight * total * total, 1.0, stride=4), cell, ok)

    def describe(self) -> str:
        return f"{self.resolution}^3 cells x one vMF lobe, {self.memory() / 2**20:.2f} MiB"


def media_bounds(scene: mi.Scene):
    """The box over which a scene's media are guided: the union of the bounds of every
    shape that bounds a medium; the scene's bounds where none does or where the camera
    sits in a medium (the medium may then reach beyond its shapes)."""
    box = mi.ScalarBoundingBox3f()
    for shape in scene.shapes():
        if shape.interior_medium() is not None or shape.exterior_medium() is not None:
            box.expand(shape.bbox())
    sensors = scene.sensors()
    if not box.valid() or any(s.get_medium() is not None for s in sensors):
        return scene_bounds(scene)
    return box


def scene_bounds(scene: mi.Scene):
    """The union of the scene's shapes' bounds. ``Scene.bbox()`` can miss shapes: Mitsuba
    merges meshes that share a BSDF into one whose ``bbox()`` is empty from Python
    (measured: a room of rectangles reported the light's bounds alone), so a merged mesh
    is bounded by its vertices."""
    box = mi.ScalarBoundingBox3f()
    for shape in scene.shapes():
        b = shape.bbox()
        if b.valid():
            box.expand(b)
        elif shape.is_mesh() and shape.vertex_count() > 0:
            v = np.array(shape.vertex_positions_buffer()).reshape(-1, 3)
            box.expand(mi.ScalarBoundingBox3f(v.min(axis=0).tolist(), v.max(axis=0).tolist()))
    return box if box.valid() else scene.bbox()


def rectangle_solid_angle(u0, u1, v0, v1, h) -> np.ndarray:
    """The solid angle of the rectangle ``[u0, u1] x [v0, v1]`` in a plane at distance
    ``h > 0`` from a point whose foot on the plane is the origin (the sum over its corners
    of ``+- atan(u v / (h sqrt(u^2 + v^2 + h^2)))``; 0 where ``h`` is 0)."""
    h = np.asarray(h, np.float64)
    hs = np.where(h > 0, h, 1.0)

    def corner(u, v):
        return np.arctan(u * v / (hs * np.sqrt(u * u + v * v + hs * hs)))
    omega = corner(u1, v1) - corner(u0, v1) - corner(u1, v0) + corner(u0, v0)
    return np.where(h > 0, np.abs(omega), 0.0)


def geometry_planes(scene: mi.Scene, most: int = 0) -> list:
    """Per axis, the coordinates of the scene's own planes normal to it (a wall, a floor:
    the faces of its meshes whose normal lies along the axis, merged where they share a
    coordinate), the ``most`` largest by area (default :data:`PORTAL_GEOMETRY_PLANES`):
    an opening in a wall lies in the wall's plane, where the rays through it have their
    waist (:meth:`HistogramField.portals`). Shapes other than meshes add none."""
    most = most or PORTAL_GEOMETRY_PLANES
    coords, areas = [[], [], []], [[], [], []]
    for shape in scene.shapes():
        if not shape.is_mesh() or shape.face_count() == 0:
            continue
        v = np.array(shape.vertex_positions_buffer(), np.float64).reshape(-1, 3)
        f = np.array(shape.faces_buffer(), np.int64).reshape(-1, 3)
        cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        area = 0.5 * np.linalg.norm(cross, axis=1)
        for axis in range(3):
            along = (area > 0) & (np.abs(cross[:, axis]) >= (1.0 - 1e-6) * 2.0 * area)
            coords[axis].append(v[f[along]][:, :, axis].mean(axis=1))
            areas[axis].append(area[along])
    out = []
    for axis in range(3):
        c = np.concatenate(coords[axis]) if coords[axis] else np.zeros(0)
        a = np.concatenate(areas[axis]) if areas[axis] else np.zeros(0)
        if c.size == 0:
            out.append(np.zeros(0))
            continue
        keys, inverse = np.unique(np.round(c, 5), return_inverse=True)
        total = np.bincount(inverse, weights=a)
        out.append(np.sort(keys[np.argsort(-total, kind="stable")[:most]]))
    return out


#: default bins per axis of :class:`HistogramField`'s directional histograms (path_rr's
#: ``guiding_bins``)
BINS = 16
#: portals (:meth:`HistogramField.portals`): records kept per cell by each training
#: pass (one per path, the slot that brought it the most light; at most PORTAL_BUFFER
#: in all), candidate planes per axis across the field's box where the scene has none of
#: its own, and the half-width, in standard deviations of a plane's crossings, of the
#: rectangle that scores the plane (a uniform interval of half-width sqrt(3) has a
#: standard deviation of 1). Tuning room (`benchmarks.guiding --surfaces --set tuning
#: --spp 256 --runs 6`, efficiency against `path`, relMSE per sample; one portal per
#: cell, from planes across the box, the rectangle the scoring one): 64 rows, 1.5 sqrt(3)
#: wide: 1.69x (0.38) against 1.44x (0.49) without portals; 256 rows 1.79x (0.37) against
#: 1.71x (0.46); 256 rows, sqrt(3) wide: 1.67x (0.39) against 1.55x (0.48)
PORTAL_ROWS = 256
PORTAL_BUFFER = 1 << 18
PORTAL_PLANES = 32
PORTAL_WIDTH = 1.5 * math.sqrt(3.0)
#: ... the least share of a pool's recorded light that must cross a portal, and the
#: largest solid angle (sr, from the pool's centre) its scoring rectangle may cover
PORTAL_SHARE = 0.3
PORTAL_SOLID_ANGLE = 1.0
#: ... the least effective number of records (``(sum w)^2 / sum w^2``) behind a portal,
#: and its least half-width, a share of a cell's smallest side
PORTAL_MIN_RECORDS = 16
PORTAL_MIN_WIDTH = 0.25
#: ... the light-weighted quantiles of a chosen plane's crossings that bound its portal
#: (each axis: from PORTAL_TRIM to 1 - PORTAL_TRIM, widened by 1 / (1 - 2 PORTAL_TRIM), so
#: that uniform crossings give their own interval), and the share of a ray's length before
#: its next vertex within which a plane does not count as crossed
PORTAL_TRIM = 0.02
PORTAL_END = 1e-3
#: ... at most this many of the scene's own planes per axis are the candidates
#: (:func:`geometry_planes`: the faces whose normal lies along the axis, by area; an
#: opening in a wall lies in the wall's plane)
PORTAL_GEOMETRY_PLANES = 16
#: ... and the cells per axis whose records find one portal together (a door is the
#: waist of the bundle of a room's rays, not of one cell's; pooled, the records of a few
#: cells also weigh the door's share of the light with less noise)
PORTAL_POOL = 2
#: floats per kept record: cell, position, direction, distance to the next vertex, value
#: (and spares: one packet scatter of a power of two)
PORTAL_STRIDE = 16
#: ... and the most records the host keeps from the passes so far (the newest; 9 floats
#: each). Every training pass keeps records and the portals are found anew after each,
#: from all of them: on the tuning room (ad-hoc, 128x128, 256 spp, 4 renders, relMSE
#: per sample over plain path_rr's) the last training pass's records alone gave 0.26,
#: with the pass before it 0.21, with every pass 0.18; the last pass with 4x as many
#: rows 0.26: what pays is portals in the training passes and records of several fields
PORTAL_KEPT = 1 << 18


class HistogramField(GuidingField):
    """Spatial grid x one directional histogram per cell: ``bins x bins`` equal-area bins
    over the sphere (``z = cos theta`` and ``phi`` in equal steps, world axes: each bin
    covers ``4 pi / bins^2`` sr), mixed with the uniform distribution (:data:`BIN_UNIFORM`).
    Sampling picks a bin by its cell's cumulative table (a guide table into it) and a
    point uniformly in it, so the density is the bin's probability over its solid angle:
    exact. Bin ``b`` of a cell learns the sum of its records' values: ``path_rr``'s
    surface records are ``f cos Li / p`` (``path_loop.SURFACE_PRODUCT``), an unbiased
    estimate of the reflected light's integrand integrated over the bin, so the histogram
    follows the product of incident light and BSDF that the mixture samples toward. The
    lobe's moments are still fitted (they say which cells are trained).

    Why for surfaces: where light arrives through a narrow opening one lobe per cell is
    too broad (mean cosines 0.2-0.5 in a room lit through a slit). A surface path's
    weights do not compound over tens of vertices as a medium's do, so the histogram's
    resolution is worth its noise there (measured: docs/benchmarks.md); in media it is
    not (module docstring)."""

    #: the plain moment fit: here the lobes only say which cells are trained, and the
    #: surfaces' defaults were chosen with it
    NOISE_AWARE = False

    def __init__(self, bbox, resolution: int = RESOLUTION, bins: int = BINS):
        self.bins = int(bins)
        self.size = self.bins * self.bins
        self.hist = None
        self.portal_source = None    # the records the portals were found from (host)
        self.portal_buffer = None    # the device buffer of the pass that keeps them
        # per axis, the scene's own planes among the portals' candidates (geometry_planes)
        self.geometry_planes = [np.zeros(0)] * 3
        super().__init__(bbox, resolution)
        self.hist = np.zeros((self.cells, self.size), np.float64)

    def memory(self) -> int:
        return field_bytes(self.resolution, self.bins)

    def _upload(self, mu, kappa, fluence=None, nee=None) -> None:
        super()._upload(mu, kappa, fluence, nee)
        prob = np.full((self.cells, self.size), 1.0 / self.size)
        if self.hist is not None:
            total = self.hist.sum(axis=1, keepdims=True)
            trained = (kappa > 0)[:, None] & (total > 0)
            learnt = (1.0 - BIN_UNIFORM) * self.hist / np.where(total > 0, total, 1.0) + \
                BIN_UNIFORM / self.size
            prob = np.where(trained, learnt, prob)
        cdf = np.cumsum(prob, axis=1)
        cdf[:, -1] = 1.0
        # start[c, j]: the first bin of cell c whose cumulative probability (as the
        # device holds it, float32) reaches j / size less 1e-6: no u that the device
        # maps to interval j (floor(u * size) in float32, which may round a u just below
        # j / size up to j) falls in an earlier bin
        cdf32 = cdf.astype(np.float32).astype(np.float64)
        offset = 2.0 * np.arange(self.cells)[:, None]       # rows apart, still sorted
        start = np.searchsorted((cdf32 + offset).ravel(),
                                (np.arange(self.size) / self.size - 1e-6 + offset).ravel())
        start = start.reshape(self.cells, self.size) - \
            self.size * np.arange(self.cells)[:, None]
        self.start = mi.UInt32(np.clip(start, 0, self.size - 1).astype(np.uint32).ravel())
        self.prob = mi.Float(prob.ravel().astype(np.float32))
        self.cdf = mi.Float(cdf.ravel().astype(np.float32))
        self.acc_hist = dr.zeros(mi.Float, self.cells * self.size)
        table = self.portals() if getattr(self, "portal_source", None) is not None \
            else np.zeros((self.cells, 6))
        table[~(kappa > 0)] = 0.0
        # whether any cell has a portal: passes before that trace none
        self.has_portals = bool((table[:, 3:] > 0).any())
        # per cell 8 floats (one packet gather): centre, half-extents, 1 / area, a spare
        packed_table = np.zeros((self.cells, 8))
        packed_table[:, :6] = table
        h = table[:, 3:]
        area = 4.0 * np.prod(np.where(h > 0, h, 1.0), axis=1)
        packed_table[:, 6] = np.where((h > 0).sum(axis=1) == 2, 1.0 / area, 0.0)
        self.portal_table = mi.Float(packed_table.ravel().astype(np.float32))
        dr.eval(self.prob, self.cdf, self.start, self.acc_hist, self.portal_table)

    def keep_portal_records(self) -> None:
        """The next pass hands :meth:`record_portal` its records (a fresh buffer); the
        update after it finds the portals from them and those the passes before kept
        (:meth:`portals`)."""
        self.portal_rows = max(4, min(PORTAL_ROWS, PORTAL_BUFFER // self.cells))    # per cell
        self.portal_buffer = dr.zeros(mi.Float, self.cells * self.portal_rows * PORTAL_STRIDE)
        dr.eval(self.portal_buffer)      # (a literal target would split the pass's kernel)

    def update(self) -> int:
        self.hist += np.array(self.acc_hist, np.float64).reshape(self.cells, self.size)
        if self.portal_buffer is not None:
            # this pass's records join those of the passes before (the newest PORTAL_KEPT)
            fresh = np.array(self.portal_buffer, np.float32).reshape(-1, PORTAL_STRIDE)[:, :9]
            fresh = fresh[fresh[:, 8] > 0]
            if self.portal_source is not None:
                fresh = np.concatenate([self.portal_source, fresh])
            self.portal_source = fresh[-PORTAL_KEPT:]
            self.portal_buffer = None
        return super().update()

    # -- portals: a rectangle through which most of a cell's light arrives ---------------
    def portals(self) -> np.ndarray:
        """Per cell, a portal ``(centre, half-extents)`` (6 numbers: an axis-aligned
        rectangle, one half-extent 0 along its normal), or zeros where none. From the kept
        records (:meth:`record_portal`) of each pool of ``PORTAL_POOL^3`` cells together:
        for each axis and each candidate plane normal to it (the scene's own,
        :attr:`geometry_planes`, or where it has none :data:`PORTAL_PLANES` across the
        field's box), the crossings of the records' rays (beyond a cell's width from their
        origin and before their next vertex), weighted by the light each brought. The
        plane chosen maximises ``share^2 / solid angle`` (a technique that samples a solid
        angle ``Omega`` carrying the share ``s`` of the light uniformly has a second moment
        ``s^2 / Omega`` times that of the BSDF's cosine; here ``Omega`` is that of the
        crossings' mean +- ``PORTAL_WIDTH`` standard deviations from the pool's centre,
        :func:`rectangle_solid_angle`), among those crossed by at least
        :data:`PORTAL_SHARE` of the pool's light and covering at most
        :data:`PORTAL_SOLID_ANGLE` sr. The portal then spans that plane's crossings between
        their light-weighted :data:`PORTAL_TRIM` and ``1 - PORTAL_TRIM`` quantiles per
        axis (:meth:`_trimmed`), for every cell of the pool. A door in a wall: the door,
        for the cells of the room behind it."""
        out = np.zeros((self.cells, 6))
        rec = self.portal_source
        cell = rec[:, 0].astype(np.int64)
        ok = (rec[:, 8] > 0) & np.isfinite(rec).all(axis=1) & (cell >= 0) & (cell < self.cells)
        if not ok.any():
            return out
        rec, cell = rec[ok], cell[ok]
        x, d, t, w = rec[:, 1:4], rec[:, 4:7], rec[:, 7], rec[:, 8]
        size = 1.0 / (np.array(self.inv_size) * self.resolution)       # a cell's sides
        lo = np.array(self.lo)
        # the records of PORTAL_POOL^3 neighbouring cells find one portal together
        r, q = self.resolution, PORTAL_POOL
        rq = -(-r // q)
        pool_of = lambda c: (c % r) // q + ((c // r) % r) // q * rq + (c // (r * r)) // q * rq * rq
        owner = pool_of(np.arange(self.cells))
        cell, n = pool_of(cell), rq ** 3
        i = np.stack([np.arange(n) % rq, (np.arange(n) // rq) % rq, np.arange(n) // (rq * rq)], 1)
        centres = lo + np.minimum((i + 0.5) * q, 0.5 * (r + (i * q))) * size
        out = np.zeros((n, 6))
        total = np.bincount(cell, weights=w, minlength=n)
        best = np.zeros(n)
        chosen_axis, chosen_plane = np.full(n, -1), np.zeros(n)
        for axis in range(3):
            a, b = [k for k in range(3) if k != axis]
            # the scene's own planes normal to the axis, or where it has none, planes
            # evenly across the field's box
            planes = self.geometry_planes[axis] if len(self.geometry_planes[axis]) else \
                lo[axis] + (np.arange(PORTAL_PLANES) + 0.5) * \
                (size[axis] * self.resolution / PORTAL_PLANES)
            count = len(planes)
            m = n * count
            per = np.arange(m) // count          # each (cell, plane) key's cell
            s_all = self._crossing(planes[None, :], x[:, axis, None], d[:, axis, None],
                                   t[:, None], np.max(size))
            flat = np.flatnonzero(np.isfinite(s_all))
            if flat.size == 0:
                continue
            r, k = flat // count, flat % count
            sc, wc = s_all.ravel()[flat], w[r]
            u, v = x[r, a] + sc * d[r, a], x[r, b] + sc * d[r, b]
            key = cell[r] * count + k
            W = np.bincount(key, weights=wc, minlength=m)
            W2 = np.bincount(key, weights=wc * wc, minlength=m)
            Wd = np.where(W > 0, W, 1.0)
            mu = np.bincount(key, weights=wc * u, minlength=m) / Wd
            mv = np.bincount(key, weights=wc * v, minlength=m) / Wd
            vu = np.maximum(np.bincount(key, weights=wc * u * u, minlength=m) / Wd - mu * mu, 0)
            vv = np.maximum(np.bincount(key, weights=wc * v * v, minlength=m) / Wd - mv * mv, 0)
            hu = np.maximum(PORTAL_WIDTH * np.sqrt(vu), PORTAL_MIN_WIDTH * np.min(size))
            hv = np.maximum(PORTAL_WIDTH * np.sqrt(vv), PORTAL_MIN_WIDTH * np.min(size))
            share = W / np.where(total[per] > 0, total[per], 1.0)
            ess = W * W / np.where(W2 > 0, W2, 1.0)
            # the rectangle's solid angle from the pool's centre
            gap = np.abs(np.tile(planes, n) - centres[per, axis])
            du, dv = mu - centres[per, a], mv - centres[per, b]
            omega = rectangle_solid_angle(du - hu, du + hu, dv - hv, dv + hv, gap)
            score = np.where((share >= PORTAL_SHARE) & (omega < PORTAL_SOLID_ANGLE) &
                             (omega > 0) & (ess >= PORTAL_MIN_RECORDS),
                             share * share / np.maximum(omega, 1e-12), 0.0)
            score = score.reshape(n, count)
            k_best = np.argmax(score, axis=1)
            top = score[np.arange(n), k_best]
            better = top > best
            chosen_axis[better], chosen_plane[better] = axis, planes[k_best[better]]
            best = np.where(better, top, best)
        for axis in range(3):
            a, b = [k for k in range(3) if k != axis]
            r = np.flatnonzero(chosen_axis[cell] == axis)
            if r.size == 0:
                continue
            c = cell[r]
            s = self._crossing(chosen_plane[c], x[r, axis], d[r, axis], t[r], np.max(size))
            keep = np.isfinite(s)
            r, c, s = r[keep], c[keep], s[keep]
            centre = np.zeros((n, 3))
            centre[:, axis] = chosen_plane
            half = np.zeros((n, 3))
            for e in (a, b):
                lo_e, hi_e = self._trimmed(c, x[r, e] + s * d[r, e], w[r], n)
                centre[:, e] = 0.5 * (lo_e + hi_e)
                half[:, e] = np.maximum(0.5 * (hi_e - lo_e) / (1.0 - 2.0 * PORTAL_TRIM),
                                        PORTAL_MIN_WIDTH * np.min(size))
            mine = chosen_axis == axis
            out[mine, :3], out[mine, 3:] = centre[mine], half[mine]
        return out[owner]

    @staticmethod
    def _crossing(plane, x, d, t, start: float) -> np.ndarray:
        """Where the ray ``x + s d`` (one axis) crosses ``plane``: ``s``, or NaN unless
        ``start < s < t (1 - PORTAL_END)`` (beyond a cell's width from its origin, and
        clearly before its next vertex: a ray that ended on a wall in that plane did not
        cross it)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (plane - x) / d
        return np.where((s > start) & (s < t * (1.0 - PORTAL_END)) & np.isfinite(s), s, np.nan)

    @staticmethod
    def _trimmed(group: np.ndarray, value: np.ndarray, weight: np.ndarray, n: int):
        """Per group in ``[0, n)``, the ``weight``-weighted :data:`PORTAL_TRIM` and ``1 -
        PORTAL_TRIM`` quantiles of ``value`` (zeros for a group without values)."""
        lo, hi = np.zeros(n), np.zeros(n)
        if group.size == 0:
            return lo, hi
        order = np.lexsort((value, group))
        g, v, wt = group[order], value[order], weight[order]
        first = np.searchsorted(g, g, side="left")
        cum = np.cumsum(wt)
        before = np.where(first > 0, cum[first - 1], 0.0)
        tot = np.bincount(g, weights=wt, minlength=n)
        frac = (cum - before - 0.5 * wt) / np.maximum(tot[g], 1e-300)
        key = 2.0 * g + np.clip(frac, 0.0, 1.0)           # sorted: groups 2 apart
        groups = np.unique(g)
        start = np.searchsorted(g, groups, side="left")
        end = np.searchsorted(g, groups, side="right") - 1
        i_lo = np.clip(np.searchsorted(key, 2.0 * groups + PORTAL_TRIM), start, end)
        i_hi = np.clip(np.searchsorted(key, 2.0 * groups + 1.0 - PORTAL_TRIM, side="right") - 1,
                       start, end)
        lo[groups], hi[groups] = v[i_lo], v[np.maximum(i_hi, i_lo)]
        return lo, hi

    def portal(self, cell: mi.UInt32, active=True):
        """``(centre, half-extents, 1 / area)`` of ``cell``'s portal (:meth:`portals`; 1 /
        area 0 where none)."""
        v = dr.gather(mi.ArrayXf, self.portal_table, cell, active, shape=(8, dr.width(cell)))
        return mi.Point3f(v[0], v[1], v[2]), mi.Vector3f(v[3], v[4], v[5]), v[6]

    @staticmethod
    def portal_sample(centre: mi.Point3f, half: mi.Vector3f, u: mi.Point2f) -> mi.Point3f:
        """A point uniform on the rectangle (its normal's half-extent is 0; the other two
        axes take ``u.x``, ``u.y`` in order)."""
        first = half.x > 0
        second = dr.select(first, dr.select(half.y > 0, 1, 2), 2)
        e = [mi.Float(0.0), mi.Float(0.0), mi.Float(0.0)]
        ux, uy = 2.0 * u.x - 1.0, 2.0 * u.y - 1.0
        e[0] = dr.select(first, ux, 0.0)
        e[1] = dr.select(~first, ux, dr.select(second == 1, uy, 0.0))
        e[2] = dr.select(second == 2, uy, 0.0)
        return centre + half * mi.Vector3f(*e)

    @staticmethod
    def portal_pdf(centre: mi.Point3f, half: mi.Vector3f, inv_area: mi.Float, x: mi.Point3f,
                   d: mi.Vector3f) -> mi.Float:
        """The solid-angle density at ``x`` of the unit direction ``d`` toward a point
        uniform on the rectangle: ``t^2 / (A |cos|)`` where the ray ``x + t d`` (``t >
        0``) crosses it, else 0."""
        normal = mi.Vector3f(dr.select(half.x > 0, 0.0, 1.0), dr.select(half.y > 0, 0.0, 1.0),
                             dr.select(half.z > 0, 0.0, 1.0))
        cos = dr.dot(d, normal)
        t = dr.dot(centre - x, normal) / dr.select(dr.abs(cos) > 1e-9, cos, 1e-9)
        off = dr.abs(x + t * d - centre)
        # (a relative 1e-6 more: a point drawn on the edge, found again by the ray, may
        # round a hair outside)
        inside = dr.all((off <= half * (1.0 + 1e-6)) | (normal > 0))
        ok = (dr.abs(cos) > 1e-9) & (t > 0) & inside & (inv_area > 0)
        return dr.select(ok, t * t * inv_area / dr.abs(cos), 0.0)

    def record_portal(self, lane: mi.UInt32, cell: mi.UInt32, p: mi.Point3f, d: mi.Vector3f,
                      t: mi.Float, value: mi.Float, active) -> None:
        """Keep a record (its ray from ``p`` along ``d`` to its next vertex at ``t``, and
        the light ``value`` it brought) in one of ``cell``'s rows of the pass's buffer
        (:meth:`keep_portal_records`), chosen by a hash of ``lane``: where several
        records share a row, one of them stays (a per-cell subsample, for :meth:`portals`)."""
        ok = active & dr.isfinite(value) & (value > 0)
        row = cell * self.portal_rows + (mi.UInt32(lane * 2654435761) >> 16) % self.portal_rows
        dr.scatter(self.portal_buffer, packed(
            mi.Float(cell), p.x, p.y, p.z, d.x, d.y, d.z, dr.minimum(t, 1e30), value,
            stride=PORTAL_STRIDE), row, ok)

    def _bin(self, d: mi.Vector3f) -> mi.UInt32:
        n = self.bins
        iz = dr.clip(mi.Int32(dr.floor((d.z + 1.0) * (0.5 * n))), 0, n - 1)
        phi = dr.atan2(d.y, d.x)
        phi = dr.select(phi < 0, phi + 2 * math.pi, phi)
        ip = dr.clip(mi.Int32(dr.floor(phi * (n / (2 * math.pi)))), 0, n - 1)
        return mi.UInt32(iz * n + ip)

    def lookup(self, cell, active=True):
        base = cell * self.size
        return lambda d: dr.gather(mi.Float, self.prob, base + self._bin(d), active) * \
            (self.size / (4 * math.pi))

    def find_bin(self, cell, u: mi.Float, active=True) -> mi.UInt32:
        """The first bin of ``cell`` whose cumulative probability reaches ``u``. The
        guide table (Chen and Asau 1974) gives the first bin that can be it, from the
        interval of ``u``; the loop steps from there (each bin holds at least
        BIN_UNIFORM / size, so at most 1 / BIN_UNIFORM + 2 steps): the same bin as a
        binary search, in fewer gathers."""
        base = cell * self.size
        j = dr.minimum(mi.UInt32(u * self.size), self.size - 1)
        b = dr.gather(mi.UInt32, self.start, base + j, active)
        return dr.while_loop(
            (b,), lambda b: active & (b < self.size - 1) &
            (dr.gather(mi.Float, self.cdf, base + b, active) < u),
            lambda b: (b + 1,), label="guide_table")[0]

    def sample(self, cell, u: mi.Point2f, active=True) -> mi.Vector3f:
        """A direction: ``u.x`` chooses the bin and is reused for ``z`` within it,
        ``u.y`` gives ``phi`` within it."""
        base = cell * self.size
        b = self.find_bin(cell, u.x, active)
        hi = dr.gather(mi.Float, self.cdf, base + b, active)
        p = dr.gather(mi.Float, self.prob, base + b, active)
        x = dr.clip(1.0 - (hi - u.x) / dr.maximum(p, 1e-30), 0.0, 0.99999)
        n = self.bins
        z = dr.clip((mi.Float(b // n) + x) * (2.0 / n) - 1.0, -1.0, 1.0)
        phi = (mi.Float(b % n) + dr.clip(u.y, 0.0, 0.99999)) * (2 * math.pi / n)
        s = dr.safe_sqrt(1.0 - z * z)
        return mi.Vector3f(s * dr.cos(phi), s * dr.sin(phi), z)

    def record(self, cell, d, value, active, weight=1.0) -> None:
        super().record(cell, d, value, active, weight)
        ok = active & dr.isfinite(value) & (value >= 0)
        dr.scatter_reduce(dr.ReduceOp.Add, self.acc_hist, value,
                          cell * self.size + self._bin(d), ok)

    def describe(self) -> str:
        return (f"{self.resolution}^3 cells x {self.bins}x{self.bins} directional bins, "
                f"{self.memory() / 2**20:.2f} MiB")
