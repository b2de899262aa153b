// Python bindings of the model writer and decoder (part of vastray.native).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <array>
#include <limits>
#include <stdexcept>
#include <string>

#include "vastray/model_decode.h"
#include "vastray/model_writer.h"
#include "writer/level_files.h"

namespace py = pybind11;
using namespace vastray;

namespace {

using FloatArray = py::array_t<float, py::array::c_style | py::array::forcecast>;
using DoubleArray = py::array_t<double, py::array::c_style | py::array::forcecast>;
using UIntArray = py::array_t<std::uint32_t, py::array::c_style | py::array::forcecast>;

Box3f to_box(const std::vector<double>& lo, const std::vector<double>& hi) {
    if (lo.size() != 3 || hi.size() != 3) throw std::invalid_argument("cell corners must have three components");
    Box3f b;
    for (int a = 0; a < 3; ++a) {
        b.lo[a] = static_cast<float>(lo[static_cast<std::size_t>(a)]);
        b.hi[a] = static_cast<float>(hi[static_cast<std::size_t>(a)]);
    }
    if (b.empty()) throw std::invalid_argument("cell is empty (lo > hi)");
    return b;
}

class PyModelWriter {
public:
    PyModelWriter(bool has_colours, const std::string& scratch_dir, py::object progress, int leaf_size,
                  float traversal_cost, float intersection_cost, float empty_space_ratio, int bins, int voxel_rays,
                  unsigned threads)
        : files_(scratch_dir) {
        ModelWriterParams p;
        p.has_colours = has_colours;
        p.kd.leaf_size = leaf_size;
        p.kd.traversal_cost = traversal_cost;
        p.kd.intersection_cost = intersection_cost;
        p.kd.empty_space_ratio = empty_space_ratio;
        p.kd.bins = bins;
        p.kd.threads = threads;
        p.voxel_rays_per_axis = voxel_rays;
        if (leaf_size < 1 || !(traversal_cost > 0) || !(intersection_cost > 0) || bins < 2 || voxel_rays < 1) {
            throw std::invalid_argument("invalid model build parameters");
        }
        // Blocks go straight to the level files, without the GIL.
        BlockSink block_sink = [this](int level, StoredBlock&& block) { files_.write(level, block); };
        ProgressSink progress_sink;
        if (!progress.is_none()) {
            progress_sink = [progress](std::uint64_t refs) {
                py::gil_scoped_acquire gil;
                progress(refs);
            };
        }
        writer_ = std::make_unique<ModelWriter>(p, std::move(block_sink), std::move(progress_sink));
    }

    int add_subtree(FloatArray corners, UIntArray ids, py::object colours, const std::vector<double>& lo,
                    const std::vector<double>& hi, int level) {
        const auto n = static_cast<std::size_t>(corners.size() / 9);
        if (corners.size() % 9 != 0 || corners.ndim() < 2) throw std::invalid_argument("corners must have shape (n, 9) or (n, 3, 3)");
        if (static_cast<std::size_t>(ids.size()) != n) throw std::invalid_argument("ids must have one entry per triangle");
        UIntArray colour_array;
        const std::uint32_t* colour_ptr = nullptr;
        if (!colours.is_none()) {
            colour_array = UIntArray::ensure(colours);
            if (!colour_array || static_cast<std::size_t>(colour_array.size()) != n) {
                throw std::invalid_argument("colours must be one uint32 per triangle");
            }
            colour_ptr = colour_array.data();
        }
        if (level < 0) throw std::invalid_argument("level must be >= 0");
        const Box3f cell = to_box(lo, hi);
        py::gil_scoped_release release;
        return writer_->add_subtree(corners.data(), ids.data(), colour_ptr, n, cell, level);
    }

    int add_inner_treelet(int level, const std::vector<double>& lo, const std::vector<double>& hi,
                          const std::array<int, 7>& axes, const std::array<float, 7>& splits,
                          const std::array<int, 8>& children) {
        const Box3f cell = to_box(lo, hi);
        py::gil_scoped_release release;
        return writer_->add_inner_treelet(level, cell, axes, splits, children);
    }

    void finish(int root) {
        py::gil_scoped_release release;
        writer_->finish(root);
        files_.close();
    }

    // {level: (file path, (n, 4) uint32 of stored size, raw size, crc32, codec)}; level
    // -1 is the triangle level.
    py::dict levels() const {
        py::dict d;
        for (const auto& [level, entries] : files_.entries()) {
            py::array_t<std::uint32_t> a({static_cast<py::ssize_t>(entries.size()), py::ssize_t{4}});
            std::memcpy(a.mutable_data(), entries.data(), entries.size() * sizeof entries[0]);
            d[py::int_(level)] = py::make_tuple(files_.path(level), a);
        }
        return d;
    }

    py::dict stats() const {
        const ModelWriterStats& s = writer_->stats();
        py::dict d;
        d["basic_nodes"] = s.basic_nodes;
        d["lod_nodes"] = s.lod_nodes;
        d["leaves"] = s.leaves;
        d["empty_children"] = s.empty_children;
        d["voxels_one"] = s.voxels_one;
        d["voxels_six"] = s.voxels_six;
        d["treelets"] = s.treelets;
        d["references"] = s.references;
        d["stored_triangles"] = s.stored_triangles;
        d["stored_vertices"] = s.stored_vertices;
        d["degenerate"] = s.degenerate;
        d["triangle_blocks"] = s.triangle_blocks;
        d["triangle_bytes"] = s.triangle_bytes;
        d["level_blocks"] = s.level_blocks;
        d["level_bytes"] = s.level_bytes;
        d["level_nodes"] = s.level_nodes;
        d["level_voxels"] = s.level_voxels;
        d["kd_build_ms"] = s.kd_build_ms;
        d["emit_ms"] = s.emit_ms;
        d["max_depth"] = s.max_depth;
        return d;
    }

private:
    writer::LevelFiles files_;  // declared first: the writer's sink writes into it
    std::unique_ptr<ModelWriter> writer_;
};

std::shared_ptr<Scene> decode(const py::list& blocks, const std::vector<std::uint32_t>& level_first,
                              const std::vector<double>& centre, const std::vector<double>& lo,
                              const std::vector<double>& hi, std::uint64_t triangle_ids, bool has_colours) {
    DecodeInput in;
    std::vector<std::string_view> views;
    for (const py::handle& b : blocks) {
        const std::string_view v = b.cast<py::bytes>();
        in.blocks.push_back(reinterpret_cast<const std::uint8_t*>(v.data()));
        in.sizes.push_back(v.size());
    }
    in.level_first = level_first;
    if (centre.size() != 3) throw std::invalid_argument("centre must have three components");
    in.centre = {centre[0], centre[1], centre[2]};
    in.root_cell = to_box(lo, hi);
    in.triangle_ids = triangle_ids;
    in.has_colours = has_colours;
    for (std::uint32_t f : level_first) {
        if (f > in.blocks.size()) throw std::invalid_argument("level starts past the last block");
    }
    py::gil_scoped_release release;  // `blocks` keeps every bytes object alive meanwhile
    return decode_model(in);
}

// One chunk of an out-of-core split pass: sorts triangle records (9 float32 corners
// first, then any payload) into the eight cells below three median-split levels (heap
// order, as ModelWriter::add_inner_treelet), copying each record to every cell whose
// closed half-spaces its bounding box touches. Returns the eight record arrays and,
// per cell, the bounds of its triangles clipped to the cell (lo xyz, hi xyz).
py::tuple sift8(const py::array_t<std::uint8_t, py::array::c_style>& records, const std::array<int, 7>& axes,
                const std::array<float, 7>& splits, FloatArray cell_lo, FloatArray cell_hi) {
    if (records.ndim() != 2 || records.shape(1) < 36) throw std::invalid_argument("records must be (n, stride >= 36) bytes");
    if (cell_lo.size() != 24 || cell_hi.size() != 24) throw std::invalid_argument("cells must be (8, 3) corners");
    for (int a : axes) {
        if (a < 0 || a > 2) throw std::invalid_argument("split axis must be 0, 1 or 2");
    }
    const auto n = static_cast<std::size_t>(records.shape(0));
    const auto stride = static_cast<std::size_t>(records.shape(1));
    const std::uint8_t* in = records.data();
    std::vector<std::uint8_t> slots(n);
    std::array<std::size_t, 8> counts{};
    float tight[8][6];
    for (auto& t : tight) {
        for (int k = 0; k < 3; ++k) {
            t[k] = std::numeric_limits<float>::infinity();
            t[3 + k] = -std::numeric_limits<float>::infinity();
        }
    }
    const float* clo = cell_lo.data();
    const float* chi = cell_hi.data();
    {
        py::gil_scoped_release release;
        for (std::size_t i = 0; i < n; ++i) {
            float c[9];
            std::memcpy(c, in + i * stride, sizeof c);
            float lo[3], hi[3];
            for (int k = 0; k < 3; ++k) {
                lo[k] = std::min({c[k], c[3 + k], c[6 + k]});
                hi[k] = std::max({c[k], c[3 + k], c[6 + k]});
            }
            bool m[15];
            m[0] = true;
            for (int h = 0; h < 7; ++h) {
                const int a = axes[static_cast<std::size_t>(h)];
                const float sp = splits[static_cast<std::size_t>(h)];
                m[2 * h + 1] = m[h] && lo[a] <= sp;
                m[2 * h + 2] = m[h] && hi[a] >= sp;
            }
            std::uint8_t bits = 0;
            for (int sl = 0; sl < 8; ++sl) {
                if (!m[7 + sl]) continue;
                bits = static_cast<std::uint8_t>(bits | (1u << sl));
                counts[static_cast<std::size_t>(sl)]++;
                float* t = tight[sl];
                for (int k = 0; k < 3; ++k) {
                    t[k] = std::min(t[k], std::max(lo[k], clo[3 * sl + k]));
                    t[3 + k] = std::max(t[3 + k], std::min(hi[k], chi[3 * sl + k]));
                }
            }
            slots[i] = bits;
        }
    }
    py::list out;
    std::vector<std::uint8_t*> dst;
    for (std::size_t sl = 0; sl < 8; ++sl) {
        py::array_t<std::uint8_t> a({static_cast<py::ssize_t>(counts[sl]), static_cast<py::ssize_t>(stride)});
        dst.push_back(a.mutable_data());
        out.append(a);
    }
    {
        py::gil_scoped_release release;
        for (std::size_t i = 0; i < n; ++i) {
            for (std::size_t sl = 0; sl < 8; ++sl) {
                if ((slots[i] >> sl) & 1u) {
                    std::memcpy(dst[sl], in + i * stride, stride);
                    dst[sl] += stride;
                }
            }
        }
    }
    py::array_t<float> bounds({8, 6});
    std::memcpy(bounds.mutable_data(), tight, sizeof tight);
    return py::make_tuple(out, bounds);
}

// The read phase's per-chunk work: builder records (9 float32 corners relative to the
// centre, computed in double as the in-core Scene does; the u32 input id; the u32
// 0x00BBGGRR colour when given) for every triangle whose float32 corners span a
// non-zero area. Returns (records as (k, stride) bytes, dropped count, kept lo, kept hi).
py::tuple make_records(DoubleArray corners, py::object colours, std::uint64_t first_id,
                       const std::vector<double>& centre) {
    if (corners.size() % 9 != 0) throw std::invalid_argument("corners must be (n, 3, 3)");
    if (centre.size() != 3) throw std::invalid_argument("centre must have three components");
    const auto n = static_cast<std::size_t>(corners.size() / 9);
    py::array_t<std::uint8_t, py::array::c_style | py::array::forcecast> rgb;
    if (!colours.is_none()) {
        rgb = py::array_t<std::uint8_t, py::array::c_style | py::array::forcecast>::ensure(colours);
        if (!rgb || static_cast<std::size_t>(rgb.size()) != 3 * n) throw std::invalid_argument("colours must be (n, 3) uint8");
    }
    const bool with_colours = !colours.is_none();
    const std::size_t stride = 36 + 4 + (with_colours ? 4 : 0);
    std::vector<std::uint8_t> out(n * stride);
    std::size_t kept = 0;
    float lo[3] = {std::numeric_limits<float>::infinity(), std::numeric_limits<float>::infinity(),
                   std::numeric_limits<float>::infinity()};
    float hi[3] = {-lo[0], -lo[1], -lo[2]};
    const double* c = corners.data();
    const std::uint8_t* col = with_colours ? rgb.data() : nullptr;
    {
        py::gil_scoped_release release;
        for (std::size_t i = 0; i < n; ++i) {
            float f[9];
            for (int k = 0; k < 9; ++k) f[k] = static_cast<float>(c[9 * i + static_cast<std::size_t>(k)] - centre[static_cast<std::size_t>(k % 3)]);
            const Vec3d a(f[0], f[1], f[2]), b(f[3], f[4], f[5]), d(f[6], f[7], f[8]);
            const Vec3d nrm = cross(b - a, d - a);
            if (nrm.x == 0 && nrm.y == 0 && nrm.z == 0) continue;  // zero area: left out, as the kd build would
            std::uint8_t* r = out.data() + kept * stride;
            std::memcpy(r, f, 36);
            const auto id = static_cast<std::uint32_t>(first_id + i);
            std::memcpy(r + 36, &id, 4);
            if (with_colours) {
                const std::uint32_t packed = static_cast<std::uint32_t>(col[3 * i]) |
                                             (static_cast<std::uint32_t>(col[3 * i + 1]) << 8) |
                                             (static_cast<std::uint32_t>(col[3 * i + 2]) << 16);
                std::memcpy(r + 40, &packed, 4);
            }
            for (int k = 0; k < 9; ++k) {
                lo[k % 3] = std::min(lo[k % 3], f[k]);
                hi[k % 3] = std::max(hi[k % 3], f[k]);
            }
            ++kept;
        }
    }
    py::array_t<std::uint8_t> records({static_cast<py::ssize_t>(kept), static_cast<py::ssize_t>(stride)});
    std::memcpy(records.mutable_data(), out.data(), kept * stride);
    return py::make_tuple(records, n - kept, std::vector<float>(lo, lo + 3), std::vector<float>(hi, hi + 3));
}

}  // namespace

void bind_model(py::module_& m) {
    py::class_<PyModelWriter>(m, "ModelWriter",
                              "Writes kd-subtrees as treelets, voxels and triangle blocks into level files in scratch_dir")
        .def(py::init<bool, const std::string&, py::object, int, float, float, float, int, int, unsigned>(),
             py::arg("has_colours"), py::arg("scratch_dir"), py::arg("progress") = py::none(), py::arg("leaf_size") = 4,
             py::arg("traversal_cost") = 1.0f, py::arg("intersection_cost") = 1.5f,
             py::arg("empty_space_ratio") = 0.15f, py::arg("bins") = 32, py::arg("voxel_rays") = 3,
             py::arg("threads") = 0u)
        .def("add_subtree", &PyModelWriter::add_subtree, py::arg("corners"), py::arg("ids"), py::arg("colours"),
             py::arg("lo"), py::arg("hi"), py::arg("level"))
        .def("add_inner_treelet", &PyModelWriter::add_inner_treelet, py::arg("level"), py::arg("lo"), py::arg("hi"),
             py::arg("axes"), py::arg("splits"), py::arg("children"))
        .def("finish", &PyModelWriter::finish, py::arg("root"))
        .def_property_readonly("levels", &PyModelWriter::levels)
        .def_property_readonly("stats", &PyModelWriter::stats);
    m.def("make_records", &make_records, py::arg("corners"), py::arg("colours"), py::arg("first_id"),
          py::arg("centre"), "Builder records for a chunk of triangles, zero-area ones left out");
    m.def("sift8", &sift8, py::arg("records"), py::arg("axes"), py::arg("splits"), py::arg("cell_lo"),
          py::arg("cell_hi"), "One chunk of an out-of-core split pass: records per cell and cell bounds");
    m.def("decode_model", &decode, py::arg("blocks"), py::arg("level_first"), py::arg("centre"), py::arg("lo"),
          py::arg("hi"), py::arg("triangle_ids"), py::arg("has_colours"),
          "Decode a whole model (raw blocks by global id) into an in-core Scene");
}
