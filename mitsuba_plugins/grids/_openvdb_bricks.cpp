// Leaf-level .vdb reader: cuts one grid of a .vdb straight into the bricks of
// mitsuba_plugins/grids/bricks.py, walking OpenVDB's leaf nodes and active tiles (never a
// dense box). Built by pip against Debian's libopenvdb-dev when it is there
// (setup.py: optional); mitsuba_plugins/grids/vdb_openvdb.py falls back to the pyopenvdb worker
// process otherwise. The result equals the worker's (tests/grids/test_vdb_files.py).
//
// info(path, address) -> dict: what the worker's info reports, without min / max; the grid
//   read stays in memory for the bricks() call on it that follows (release() frees it).
// write(path, name, data, ijk, voxel_size, compression, half): one grid, for tests.
// bricks(path, address, i0, j0, k0, nx, ny, nz) -> (coords, blocks)
//   The box is index [i0, i0 + nx) x [j0, j0 + ny) x [k0, k0 + nz) (x, y, z). Values
//   are those OpenVDB's accessor returns: leaf voxels (active or not) and active tiles;
//   elsewhere the background, which the caller has checked is 0. A brick is stored when
//   any value of its block (its BRICK^3 voxels and the high-side apron, clamped at the
//   box's end as lookups clamp) has a non-zero bit. coords: (n, 3) int32 (bz, by, bx),
//   row-major; blocks: (n, SIDE, SIDE, SIDE, C) float32, C = 1 (float) or 3 (vec3s).
#include <openvdb/openvdb.h>
#include <openvdb/io/File.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <malloc.h>

#include <array>
#include <cstdint>
#include <cstring>
#include <stdexcept>
#include <string>
#include <vector>

namespace py = pybind11;

namespace {

constexpr int BRICK = 8;
constexpr int SIDE = BRICK + 1;

// Per axis: for each box position p, the (brick, offset) slots that hold value(p).
struct Axis {
    int n = 0, bricks = 0;
    std::vector<int> start;                     // start[p] .. start[p + 1] index slots
    std::vector<std::pair<int, int>> slots;

    explicit Axis(int n_) : n(n_), bricks((n_ + BRICK - 1) / BRICK) {
        start.assign(n + 1, 0);
        int last = bricks * BRICK;              // positions 0 .. last (last: final apron)
        for (int p = 0; p < n; ++p) {
            start[p] = int(slots.size());
            int q_end = (p == n - 1) ? last : p;   // the edge value is repeated beyond
            for (int q = p; q <= q_end; ++q) {
                if (q < last) slots.emplace_back(q / BRICK, q % BRICK);
                if (q % BRICK == 0 && q > 0) slots.emplace_back(q / BRICK - 1, BRICK);
            }
        }
        start[n] = int(slots.size());
    }
};

template <typename GridT, int C>
struct Cutter {
    const Axis ax, ay, az;
    const openvdb::Coord origin;
    std::vector<int32_t> slot;                  // per brick: -1 absent, else pool slot
    float *pool = nullptr;

    Cutter(int i0, int j0, int k0, int nx, int ny, int nz)
        : ax(nx), ay(ny), az(nz), origin(i0, j0, k0),
          slot(size_t(ax.bricks) * ay.bricks * az.bricks, -1) {}

    size_t brick_index(int bz, int by, int bx) const {
        return (size_t(bz) * ay.bricks + by) * ax.bricks + bx;
    }

    static bool nonzero(const float *v) {
        for (int c = 0; c < C; ++c) {
            uint32_t bits;
            std::memcpy(&bits, v + c, 4);
            if (bits != 0) return true;
        }
        return false;
    }

    // Pass 1 (pool == nullptr): mark the bricks a voxel's value reaches; pass 2: write it.
    // (x, y, z): the voxel's position in the box.
    void voxel(int x, int y, int z, const float *v) {
        if (!nonzero(v)) return;
        for (int a = az.start[z]; a < az.start[z + 1]; ++a) {
            const auto [bz, oz] = az.slots[a];
            for (int b = ay.start[y]; b < ay.start[y + 1]; ++b) {
                const auto [by, oy] = ay.slots[b];
                for (int c = ax.start[x]; c < ax.start[x + 1]; ++c) {
                    const auto [bx, ox] = ax.slots[c];
                    int32_t &s = slot[brick_index(bz, by, bx)];
                    if (!pool) {      // leaves run in parallel: all write the same 0
                        __atomic_store_n(&s, 0, __ATOMIC_RELAXED);
                        continue;
                    }
                    float *dst = pool + ((size_t(s) * SIDE + oz) * SIDE + oy) * SIDE * C +
                                 size_t(ox) * C;
                    for (int k = 0; k < C; ++k) dst[k] = v[k];
                }
            }
        }
    }

    static const float *values(const float &v) { return &v; }
    static const float *values(const openvdb::Vec3s &v) { return v.asPointer(); }

    using LeafT = typename GridT::TreeType::LeafNodeType;

    // Leaves in parallel (a voxel's slots are its own: no two leaves write one float),
    // then the active tiles.
    void walk(const GridT &grid, const std::vector<const LeafT *> &leaves) {
        tbb::parallel_for(tbb::blocked_range<size_t>(0, leaves.size(), 64),
                          [&](const tbb::blocked_range<size_t> &range) {
                              for (size_t i = range.begin(); i < range.end(); ++i)
                                  leaf(*leaves[i]);
                          });
        tiles(grid.tree());
    }

    void leaf(const LeafT &leaf) {
        // a leaf's buffer is x-major: voxel (x, y, z) at (x << 6) | (y << 3) | z
        const auto *data = leaf.buffer().data();
        const openvdb::Coord o = leaf.origin() - origin;
        for (int lx = 0; lx < 8; ++lx) {
            const int x = o.x() + lx;
            if (x < 0 || x >= ax.n) continue;
            for (int ly = 0; ly < 8; ++ly) {
                const int y = o.y() + ly;
                if (y < 0 || y >= ay.n) continue;
                for (int lz = 0; lz < 8; ++lz) {
                    const int z = o.z() + lz;
                    if (z >= 0 && z < az.n)
                        voxel(x, y, z, values(data[(lx << 6) | (ly << 3) | lz]));
                }
            }
        }
    }

    void tiles(const typename GridT::TreeType &tree) {
        auto it = tree.cbeginValueOn();
        it.setMaxDepth(decltype(it)::LEAF_DEPTH - 1);   // tiles only, not leaf voxels
        for (; it; ++it) {
            openvdb::CoordBBox box = it.getBoundingBox();   // only its part in the box
            box.intersect(openvdb::CoordBBox(origin, origin + openvdb::Coord(ax.n - 1, ay.n - 1,
                                                                             az.n - 1)));
            if (box.empty()) continue;
            const float *v = values(*it);
            for (int z = box.min().z(); z <= box.max().z(); ++z)
                for (int y = box.min().y(); y <= box.max().y(); ++y)
                    for (int x = box.min().x(); x <= box.max().x(); ++x)
                        voxel(x - origin.x(), y - origin.y(), z - origin.z(), v);
        }
    }

    py::tuple run(const GridT &grid) {
        std::vector<const LeafT *> leaves;
        {
            py::gil_scoped_release release;
            const openvdb::CoordBBox box(origin,
                                         origin + openvdb::Coord(ax.n - 1, ay.n - 1, az.n - 1));
            for (auto it = grid.tree().cbeginLeaf(); it; ++it)
                if (box.hasOverlap(it->getNodeBoundingBox())) leaves.push_back(it.getLeaf());
            walk(grid, leaves);                       // pass 1: which bricks
        }
        int32_t n = 0;
        for (auto &s : slot)
            if (s == 0) s = n++;                      // row-major slots
        py::array_t<int32_t> coords({py::ssize_t(n), py::ssize_t(3)});
        auto cw = coords.mutable_unchecked<2>();
        for (int bz = 0, i = 0; bz < az.bricks; ++bz)
            for (int by = 0; by < ay.bricks; ++by)
                for (int bx = 0; bx < ax.bricks; ++bx)
                    if (slot[brick_index(bz, by, bx)] >= 0) {
                        cw(i, 0) = bz, cw(i, 1) = by, cw(i, 2) = bx;
                        ++i;
                    }
        std::vector<py::ssize_t> shape{n, SIDE, SIDE, SIDE};
        if (C > 1) shape.push_back(C);
        py::array_t<float> blocks(shape);
        pool = blocks.mutable_data();
        {
            py::gil_scoped_release release;
            const size_t block = size_t(SIDE) * SIDE * SIDE * C;
            tbb::parallel_for(tbb::blocked_range<size_t>(0, size_t(n), 1024),
                              [&](const tbb::blocked_range<size_t> &range) {
                                  std::memset(pool + range.begin() * block, 0,
                                              sizeof(float) * block * range.size());
                              });
            walk(grid, leaves);                       // pass 2: the values
        }
        return py::make_tuple(coords, blocks);
    }
};

// The grid info() read last, kept for the bricks() call that follows it on the same grid.
struct Kept {
    std::string path, address;
    openvdb::GridBase::Ptr grid;
} kept;

openvdb::GridBase::Ptr read_grid(const std::string &path, const std::string &address) {
    if (kept.grid && kept.path == path && kept.address == address) {
        openvdb::GridBase::Ptr grid = kept.grid;
        kept = Kept{};
        return grid;
    }
    kept = Kept{};
    openvdb::initialize();
    py::gil_scoped_release release;
    openvdb::io::File file(path);
    file.open(false);                                 // no delayed loading: read it now
    openvdb::GridBase::Ptr grid = file.readGrid(address);
    file.close();
    return grid;
}

// Frees the grid info() kept, when no bricks() call will take it (dense storage).
void release() {
    kept = Kept{};
    malloc_trim(0);
}

py::object listed(const float &v) { return py::float_(v); }
py::object listed(const openvdb::Vec3s &v) { return py::make_tuple(v[0], v[1], v[2]); }

template <typename GridT>
py::object background(const openvdb::GridBase::Ptr &base) {
    auto g = openvdb::gridPtrCast<GridT>(base);
    return g ? listed(g->background()) : py::none();
}

// What mitsuba_plugins.grids._vdb_worker's info() reports without the value range; the grid
// stays in memory for the next bricks() call on it.
py::dict info(const std::string &path, const std::string &address) {
    openvdb::GridBase::Ptr grid = read_grid(path, address);
    py::dict out;
    out["name"] = grid->getName();
    out["address"] = address;
    out["type"] = grid->valueType();
    out["class"] = openvdb::GridBase::gridClassToString(grid->getGridClass());
    const openvdb::Index64 count = grid->activeVoxelCount();
    out["active_voxels"] = count;
    py::object bg = background<openvdb::FloatGrid>(grid);
    if (bg.is_none()) bg = background<openvdb::Vec3SGrid>(grid);
    out["background"] = bg;
    if (count) {
        const openvdb::CoordBBox box = grid->evalActiveVoxelBoundingBox();
        out["index_min"] = py::make_tuple(box.min().x(), box.min().y(), box.min().z());
        out["index_max"] = py::make_tuple(box.max().x(), box.max().y(), box.max().z());
    } else {
        out["index_min"] = py::none();
        out["index_max"] = py::none();
    }
    out["min"] = py::none();
    out["max"] = py::none();
    const openvdb::math::Transform &t = grid->transform();
    out["transform_type"] = t.mapType();
    out["linear"] = t.isLinear();
    if (t.isLinear()) {
        const openvdb::Vec3d o = t.indexToWorld(openvdb::Vec3d(0, 0, 0));
        py::list rows;
        for (int r = 0; r < 3; ++r) {
            py::list row;
            for (int c = 0; c < 3; ++c) {
                openvdb::Vec3d e(0, 0, 0);
                e[c] = 1;
                row.append(t.indexToWorld(e)[r] - o[r]);
            }
            row.append(o[r]);
            rows.append(row);
        }
        rows.append(py::make_tuple(0.0, 0.0, 0.0, 1.0));
        out["index_to_world"] = rows;
    } else {
        out["index_to_world"] = py::none();
    }
    out["half_float"] = grid->saveFloatAsHalf();
    kept = Kept{path, address, grid};
    return out;
}

py::tuple bricks(const std::string &path, const std::string &address, int i0, int j0, int k0,
                 int nx, int ny, int nz) {
    if (nx <= 0 || ny <= 0 || nz <= 0) throw std::invalid_argument("empty box");
    py::tuple out;
    {
        openvdb::GridBase::Ptr base = read_grid(path, address);
        if (auto g = openvdb::gridPtrCast<openvdb::FloatGrid>(base))
            out = Cutter<openvdb::FloatGrid, 1>(i0, j0, k0, nx, ny, nz).run(*g);
        else if (auto g = openvdb::gridPtrCast<openvdb::Vec3SGrid>(base))
            out = Cutter<openvdb::Vec3SGrid, 3>(i0, j0, k0, nx, ny, nz).run(*g);
        else
            throw std::invalid_argument("grid " + address + " holds " + base->valueType() +
                                        " values; allowed: float, half, vec3s");
    }
    // The tree is freed: hand its pages back now, before the caller uploads the bricks
    // (glibc keeps freed memory otherwise; measured +100 MB of peak at 1024^3).
    malloc_trim(0);
    return out;
}

// Writes one grid as OpenVDB's own library does, with the compression chosen: files of
// every kind the readers must take (tests/grids/test_vdb_reader.py; pyopenvdb cannot choose).
// data: float32 (z, y, x) or (z, y, x, 3); voxel (i, j, k) of the file = data[k, j, i]
// placed at ijk + (i, j, k); zero values stay inactive background.
void write_grid(const std::string &path, const std::string &name,
           py::array_t<float, py::array::c_style | py::array::forcecast> data,
           std::array<int, 3> ijk, double voxel_size, const std::string &compression,
           bool half) {
    uint32_t flags;
    if (compression == "zip") flags = openvdb::io::COMPRESS_ZIP | openvdb::io::COMPRESS_ACTIVE_MASK;
    else if (compression == "blosc") flags = openvdb::io::COMPRESS_BLOSC | openvdb::io::COMPRESS_ACTIVE_MASK;
    else if (compression == "none") flags = openvdb::io::COMPRESS_NONE;
    else throw std::invalid_argument("compression '" + compression +
                                     "'; allowed: zip, blosc, none");
    const int c = data.ndim() == 4 ? int(data.shape(3)) : 1;
    if ((data.ndim() != 3 && data.ndim() != 4) || (c != 1 && c != 3))
        throw std::invalid_argument("data: (z, y, x) or (z, y, x, 3) values");
    openvdb::initialize();
    const int nz = int(data.shape(0)), ny = int(data.shape(1)), nx = int(data.shape(2));
    const float *v = data.data();
    openvdb::GridBase::Ptr grid;
    auto fill = [&](auto g, auto value) {
        auto acc = g->getAccessor();
        for (int z = 0; z < nz; ++z)
            for (int y = 0; y < ny; ++y)
                for (int x = 0; x < nx; ++x) {
                    const float *p = v + ((size_t(z) * ny + y) * nx + x) * c;
                    bool any = false;
                    for (int k = 0; k < c; ++k) any |= p[k] != 0.0f;
                    if (any)
                        acc.setValueOn(openvdb::Coord(ijk[0] + x, ijk[1] + y, ijk[2] + z),
                                       value(p));
                }
        g->setTransform(openvdb::math::Transform::createLinearTransform(voxel_size));
        g->setName(name);
        g->setSaveFloatAsHalf(half);
        grid = g;
    };
    if (c == 1) fill(openvdb::FloatGrid::create(0.0f), [](const float *p) { return p[0]; });
    else fill(openvdb::Vec3SGrid::create(openvdb::Vec3s(0.0f)),
              [](const float *p) { return openvdb::Vec3s(p[0], p[1], p[2]); });
    openvdb::io::File file(path);
    file.setCompression(flags);
    file.write({grid});
    file.close();
}

}  // namespace

PYBIND11_MODULE(_openvdb_bricks, m) {
    m.doc() = "Leaf-level .vdb reader: one grid cut into mitsuba_plugins.grids.bricks' bricks";
    m.attr("BRICK") = BRICK;
    m.attr("SIDE") = SIDE;
    m.def("info", &info, py::arg("path"), py::arg("address"));
    m.def("release", &release);
    m.def("write", &write_grid, py::arg("path"), py::arg("name"), py::arg("data"), py::arg("ijk"),
          py::arg("voxel_size"), py::arg("compression"), py::arg("half") = false);
    m.def("bricks", &bricks, py::arg("path"), py::arg("address"), py::arg("i0"),
          py::arg("j0"), py::arg("k0"), py::arg("nx"), py::arg("ny"), py::arg("nz"));
}
