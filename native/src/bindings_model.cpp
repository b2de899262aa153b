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
#include "vastray/thread_pool.h"
#include "writer/level_files.h"

namespace py = pybind11;
using namespace vastray;

void bind_ingest(py::module_& m);  // bindings_ingest.cpp

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

    // records: (n, stride) uint8, one builder record per row (read in place).
    int add_subtree(const py::array_t<std::uint8_t, py::array::c_style>& records, const std::vector<double>& lo,
                    const std::vector<double>& hi, int level) {
        if (records.ndim() != 2) throw std::invalid_argument("records must be (n, stride) bytes");
        const auto n = static_cast<std::size_t>(records.shape(0));
        const auto stride = static_cast<std::size_t>(records.shape(1));
        if (level < 0) throw std::invalid_argument("level must be >= 0");
        const Box3f cell = to_box(lo, hi);
        const std::uint8_t* data = records.data();
        py::gil_scoped_release release;
        return writer_->add_subtree(data, stride, n, cell, level);
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

// The read phase's records: per triangle its corners as float32(vertex - centre), computed
// in double as the in-core Scene does (bit-identical vertices on both paths), the u32 input
// id and, when given, the u32 0x00BBGGRR colour. Triangles whose float32 corners span no
// area are left out, as the kd build would, and counted. Runs on the pool, block by block,
// each block's kept records in input order.
struct Records {
    std::vector<std::uint8_t> bytes;
    std::size_t kept = 0, dropped = 0;
    float lo[3], hi[3];
    std::int64_t bad = -1;  // the first triangle whose corner fetch failed (a bad index)
};

template <typename Corners>
Records make_records_core(std::size_t n, const Corners& corners, const std::uint8_t* colours, const std::uint32_t* ids,
                          std::uint64_t first_id, const double centre[3]) {
    const std::size_t stride = 36 + 4 + (colours != nullptr ? 4 : 0);
    constexpr std::size_t kBlock = 1 << 15;
    const std::size_t blocks = (n + kBlock - 1) / kBlock;
    std::vector<Records> parts(blocks);
    ThreadPool::global().parallel_for(blocks, [&](std::size_t b, unsigned) {
        Records& r = parts[b];
        const std::size_t begin = b * kBlock, end = std::min(n, begin + kBlock);
        r.bytes.resize((end - begin) * stride);
        for (int k = 0; k < 3; ++k) {
            r.lo[k] = std::numeric_limits<float>::infinity();
            r.hi[k] = -std::numeric_limits<float>::infinity();
        }
        for (std::size_t i = begin; i < end; ++i) {
            double v[9];
            if (!corners(i, v)) {
                r.bad = static_cast<std::int64_t>(i);
                return;
            }
            float f[9];
            for (int k = 0; k < 9; ++k) f[k] = static_cast<float>(v[k] - centre[k % 3]);
            const Vec3d a(f[0], f[1], f[2]), bb(f[3], f[4], f[5]), d(f[6], f[7], f[8]);
            const Vec3d nrm = cross(bb - a, d - a);
            if (nrm.x == 0 && nrm.y == 0 && nrm.z == 0) {
                ++r.dropped;
                continue;
            }
            std::uint8_t* out = r.bytes.data() + r.kept * stride;
            std::memcpy(out, f, 36);
            const auto id = ids != nullptr ? ids[i] : static_cast<std::uint32_t>(first_id + i);
            std::memcpy(out + 36, &id, 4);
            if (colours != nullptr) {
                const std::uint8_t* c = colours + 3 * i;
                const std::uint32_t packed = static_cast<std::uint32_t>(c[0]) | (static_cast<std::uint32_t>(c[1]) << 8) |
                                             (static_cast<std::uint32_t>(c[2]) << 16);
                std::memcpy(out + 40, &packed, 4);
            }
            for (int k = 0; k < 9; ++k) {
                r.lo[k % 3] = std::min(r.lo[k % 3], f[k]);
                r.hi[k % 3] = std::max(r.hi[k % 3], f[k]);
            }
            ++r.kept;
        }
    });
    Records all;
    for (int k = 0; k < 3; ++k) {
        all.lo[k] = std::numeric_limits<float>::infinity();
        all.hi[k] = -std::numeric_limits<float>::infinity();
    }
    for (const Records& r : parts) {
        if (r.bad >= 0) {
            all.bad = r.bad;
            return all;
        }
        all.kept += r.kept;
        all.dropped += r.dropped;
        for (int k = 0; k < 3; ++k) {
            all.lo[k] = std::min(all.lo[k], r.lo[k]);
            all.hi[k] = std::max(all.hi[k], r.hi[k]);
        }
    }
    all.bytes.resize(all.kept * stride);
    std::size_t at = 0;
    for (const Records& r : parts) {
        std::memcpy(all.bytes.data() + at, r.bytes.data(), r.kept * stride);
        at += r.kept * stride;
    }
    return all;
}

struct RecordOptions {
    py::array_t<std::uint8_t, py::array::c_style | py::array::forcecast> rgb;
    py::array_t<std::uint32_t, py::array::c_style | py::array::forcecast> id_array;
    const std::uint8_t* colours = nullptr;
    const std::uint32_t* ids = nullptr;
    double centre[3];

    RecordOptions(const py::object& colours_, const py::object& ids_, const std::vector<double>& centre_, std::size_t n) {
        if (centre_.size() != 3) throw std::invalid_argument("centre must have three components");
        for (int k = 0; k < 3; ++k) centre[k] = centre_[static_cast<std::size_t>(k)];
        if (!colours_.is_none()) {
            rgb = decltype(rgb)::ensure(colours_);
            if (!rgb || static_cast<std::size_t>(rgb.size()) != 3 * n) throw std::invalid_argument("colours must be (n, 3) uint8");
            colours = rgb.data();
        }
        if (!ids_.is_none()) {
            id_array = decltype(id_array)::ensure(ids_);
            if (!id_array || static_cast<std::size_t>(id_array.size()) != n) throw std::invalid_argument("ids must be one uint32 per triangle");
            ids = id_array.data();
        }
    }
};

py::tuple records_result(Records&& r, bool with_colours) {
    const std::size_t stride = 36 + 4 + (with_colours ? 4 : 0);
    py::array_t<std::uint8_t> records({static_cast<py::ssize_t>(r.kept), static_cast<py::ssize_t>(stride)});
    std::memcpy(records.mutable_data(), r.bytes.data(), r.bytes.size());
    return py::make_tuple(records, r.dropped, std::vector<float>(r.lo, r.lo + 3), std::vector<float>(r.hi, r.hi + 3), r.bad);
}

// Records from corners: (n, 3, 3) float64.
py::tuple make_records(DoubleArray corners, py::object colours, py::object ids, std::uint64_t first_id,
                       const std::vector<double>& centre) {
    if (corners.size() % 9 != 0) throw std::invalid_argument("corners must be (n, 3, 3)");
    const auto n = static_cast<std::size_t>(corners.size() / 9);
    const RecordOptions o(colours, ids, centre, n);
    const double* c = corners.data();
    Records r;
    {
        py::gil_scoped_release release;
        r = make_records_core(
            n, [c](std::size_t i, double* v) { std::memcpy(v, c + 9 * i, 9 * sizeof(double)); return true; },
            o.colours, o.ids, first_id, o.centre);
    }
    return records_result(std::move(r), o.colours != nullptr);
}

// Records from vertex indices into a table of vertex records: `vertices` holds `count`
// records of `stride` bytes, coordinate k at byte offsets[k], typed types[k] ("<f4",
// ">f4", "<f8", ">f8"): a binary PLY's vertex element where it lies in the file, or a
// float64 table. The result's last field names the first triangle with an index outside
// 0 ... count - 1 (-1: none), and then no records are made.
py::tuple make_indexed_records(const py::buffer& vertices, std::size_t stride, const std::array<std::size_t, 3>& offsets,
                               const std::array<std::string, 3>& types, std::size_t count,
                               py::array_t<std::int64_t, py::array::c_style | py::array::forcecast> indices,
                               py::object colours, py::object ids, std::uint64_t first_id,
                               const std::vector<double>& centre) {
    const py::buffer_info vb = vertices.request();
    if (vb.itemsize != 1 || static_cast<std::size_t>(vb.size) < count * stride) {
        throw std::invalid_argument("vertices: a byte buffer of count * stride bytes");
    }
    bool swap[3], wide[3];
    for (int k = 0; k < 3; ++k) {
        const std::string& t = types[static_cast<std::size_t>(k)];
        if (t.size() != 3 || (t[0] != '<' && t[0] != '>') || t[1] != 'f' || (t[2] != '4' && t[2] != '8')) {
            throw std::invalid_argument("vertex coordinate types are <f4, >f4, <f8 or >f8");
        }
        wide[k] = t[2] == '8';
        swap[k] = t[0] == '>';
        if (offsets[static_cast<std::size_t>(k)] + (wide[k] ? 8 : 4) > stride) throw std::invalid_argument("vertex field past its record");
    }
    if (indices.ndim() != 2 || indices.shape(1) != 3) throw std::invalid_argument("indices must be (n, 3)");
    const auto n = static_cast<std::size_t>(indices.shape(0));
    const RecordOptions o(colours, ids, centre, n);
    const auto* base = static_cast<const std::uint8_t*>(vb.ptr);
    const std::int64_t* idx = indices.data();
    auto coord = [&](const std::uint8_t* rec, int k) -> double {
        std::uint8_t b[8];
        const std::size_t w = wide[k] ? 8 : 4;
        std::memcpy(b, rec + offsets[static_cast<std::size_t>(k)], w);
        if (swap[k]) std::reverse(b, b + w);
        if (wide[k]) {
            double d;
            std::memcpy(&d, b, 8);
            return d;
        }
        float f;
        std::memcpy(&f, b, 4);
        return f;
    };
    Records r;
    {
        py::gil_scoped_release release;
        r = make_records_core(
            n,
            [&](std::size_t i, double* v) {
                for (int c = 0; c < 3; ++c) {
                    const std::int64_t j = idx[3 * i + static_cast<std::size_t>(c)];
                    if (j < 0 || static_cast<std::uint64_t>(j) >= count) return false;
                    const std::uint8_t* rec = base + static_cast<std::size_t>(j) * stride;
                    for (int k = 0; k < 3; ++k) v[3 * c + k] = coord(rec, k);
                }
                return true;
            },
            o.colours, o.ids, first_id, o.centre);
    }
    return records_result(std::move(r), o.colours != nullptr);
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
        .def("add_subtree", &PyModelWriter::add_subtree, py::arg("records"), py::arg("lo"), py::arg("hi"),
             py::arg("level"))
        .def("add_inner_treelet", &PyModelWriter::add_inner_treelet, py::arg("level"), py::arg("lo"), py::arg("hi"),
             py::arg("axes"), py::arg("splits"), py::arg("children"))
        .def("finish", &PyModelWriter::finish, py::arg("root"))
        .def_property_readonly("levels", &PyModelWriter::levels)
        .def_property_readonly("stats", &PyModelWriter::stats);
    m.def("make_records", &make_records, py::arg("corners"), py::arg("colours"), py::arg("ids"), py::arg("first_id"),
          py::arg("centre"), "Builder records for a chunk of triangles (corners), zero-area ones left out");
    m.def("make_indexed_records", &make_indexed_records, py::arg("vertices"), py::arg("stride"), py::arg("offsets"),
          py::arg("types"), py::arg("count"), py::arg("indices"), py::arg("colours"), py::arg("ids"),
          py::arg("first_id"), py::arg("centre"),
          "Builder records for a chunk of indexed triangles, gathered from vertex records");
    bind_ingest(m);
    m.def("sift8", &sift8, py::arg("records"), py::arg("axes"), py::arg("splits"), py::arg("cell_lo"),
          py::arg("cell_hi"), "One chunk of an out-of-core split pass: records per cell and cell bounds");
    m.def("decode_model", &decode, py::arg("blocks"), py::arg("level_first"), py::arg("centre"), py::arg("lo"),
          py::arg("hi"), py::arg("triangle_ids"), py::arg("has_colours"),
          "Decode a whole model (raw blocks by global id) into an in-core Scene");
}
