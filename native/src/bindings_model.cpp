// Python bindings of the model writer and decoder (part of vastray.native).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <emmintrin.h>
#include <array>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "vastray/lz4.h"
#include "vastray/model_decode.h"
#include "vastray/model_writer.h"
#include "vastray/thread_pool.h"
#include "writer/model_blocks.h"

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
    PyModelWriter(bool has_colours, const std::string& output, std::uint64_t output_offset, py::object progress, int leaf_size,
                  float traversal_cost, float intersection_cost, float empty_space_ratio, int bins, int voxel_rays,
                  unsigned threads, bool quantized_splits, py::object vertex_steps, double tier_width,
                  int tier_coarse_octaves, py::object root_cell, bool compact_triangles, bool packed_voxels,
                  bool packed_treelets, int lz4_hc_level, bool voxel_errors, float voxel_error_floor)
        : blocks_(output, checked_offset(output_offset)) {
        ModelWriterParams p;
        p.has_colours = has_colours;
        p.kd.leaf_size = leaf_size;
        p.kd.traversal_cost = traversal_cost;
        p.kd.intersection_cost = intersection_cost;
        p.kd.empty_space_ratio = empty_space_ratio;
        p.kd.bins = bins;
        p.kd.threads = threads;
        p.kd.quantized_splits = quantized_splits;
        p.compact_triangles = compact_triangles;
        p.packed_voxels = packed_voxels;
        p.packed_treelets = packed_treelets;
        if (voxel_errors && !quantized_splits) throw std::invalid_argument("voxel errors need quantized splits");
        if (!(voxel_error_floor >= 0.0f && voxel_error_floor <= 1.0f)) {
            throw std::invalid_argument("the voxel error floor must be 0 ... 1");
        }
        p.voxel_errors = voxel_errors;
        p.voxel_error_floor = voxel_error_floor;
        if (lz4_hc_level < 0 || lz4_hc_level > kLz4HcMaxLevel) {
            throw std::invalid_argument("LZ4 HC level must be 0 ... " + std::to_string(kLz4HcMaxLevel));
        }
        p.lz4_hc_level = lz4_hc_level;
        if (!vertex_steps.is_none()) {
            const auto steps = vertex_steps.cast<std::array<float, 3>>();
            p.quantized_vertices = true;
            p.vertex_steps = Vec3f(steps[0], steps[1], steps[2]);
        }
        p.voxel_rays_per_axis = voxel_rays;
        if (!(tier_width >= 0 && tier_width <= 16) || tier_coarse_octaves < 0 || tier_coarse_octaves > 32) {
            throw std::invalid_argument("tier width must be 0 ... 16 octaves and coarse octaves 0 ... 32");
        }
        if (tier_width > 0) {
            if (root_cell.is_none()) throw std::invalid_argument("a tiered model needs its root cell");
            const auto [lo, hi] = root_cell.cast<std::pair<std::vector<double>, std::vector<double>>>();
            p.root_radius = format::cell_radius(to_box(lo, hi).extent());
            p.tier_width = tier_width;
            p.tier_coarse_octaves = tier_coarse_octaves;
        }
        if (leaf_size < 1 || !(traversal_cost > 0) || !(intersection_cost > 0) || bins < 2 || voxel_rays < 1) {
            throw std::invalid_argument("invalid model build parameters");
        }
        // Blocks go straight into the model file, without the GIL.
        BlockSink block_sink = [this](int level, std::uint32_t tier, StoredBlock&& block) { blocks_.write(level, tier, block); };
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
    // lod_parent: (lo, hi) of the LOD node above the subtree, or None at the model's root.
    int add_subtree(const py::array_t<std::uint8_t, py::array::c_style>& records, const std::vector<double>& lo,
                    const std::vector<double>& hi, int level, const py::object& lod_parent) {
        if (records.ndim() != 2) throw std::invalid_argument("records must be (n, stride) bytes");
        const auto n = static_cast<std::size_t>(records.shape(0));
        const auto stride = static_cast<std::size_t>(records.shape(1));
        if (level < 0) throw std::invalid_argument("level must be >= 0");
        const Box3f cell = to_box(lo, hi);
        Box3f parent;
        const bool has_parent = !lod_parent.is_none();
        if (has_parent) {
            const auto [plo, phi] = lod_parent.cast<std::pair<std::vector<double>, std::vector<double>>>();
            parent = to_box(plo, phi);
        }
        const std::uint8_t* data = records.data();
        py::gil_scoped_release release;
        return writer_->add_subtree(data, stride, n, cell, level, has_parent ? &parent : nullptr);
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
        blocks_.close();
    }

    // {level: ((n, 5) uint32 of stored size, raw size, crc32, codec, tier, (n,) uint64
    // offsets in the model file)} in the order written; level -1 is the triangle level.
    py::dict levels() const {
        py::dict d;
        for (const auto& [level, entries] : blocks_.entries()) {
            py::array_t<std::uint32_t> a({static_cast<py::ssize_t>(entries.size()), py::ssize_t{5}});
            std::memcpy(a.mutable_data(), entries.data(), entries.size() * sizeof entries[0]);
            const std::vector<std::uint64_t>& at = blocks_.offsets().at(level);
            py::array_t<std::uint64_t> o(static_cast<py::ssize_t>(at.size()));
            std::memcpy(o.mutable_data(), at.data(), at.size() * sizeof at[0]);
            d[py::int_(level)] = py::make_tuple(a, o);
        }
        return d;
    }

    // (path, start, end, direct): the model file, where its blocks start and end, and
    // whether they were written past the page cache.
    py::tuple output() const {
        return py::make_tuple(blocks_.path(), blocks_.start(), blocks_.end(), blocks_.direct());
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
        d["voxels_packed"] = s.voxels_packed;
        d["lod_errors_below_radius"] = s.lod_errors_below_radius;
        d["lod_error_ratio_sum"] = s.lod_error_ratio_sum;
        d["voxel_error_ms"] = s.voxel_error_ms;
        d["treelets"] = s.treelets;
        d["references"] = s.references;
        d["stored_triangles"] = s.stored_triangles;
        d["stored_vertices"] = s.stored_vertices;
        d["degenerate"] = s.degenerate;
        d["triangle_blocks"] = s.triangle_blocks;
        d["vertex_bytes"] = s.vertex_bytes;
        d["triangle_bytes"] = s.triangle_bytes;
        // Per stream: (blocks, raw bytes, nodes, voxels) by [level][tier] for the node
        // levels, (blocks, raw bytes, triangle records, vertices) by [tier] for triangles.
        auto rows = [](const std::vector<StreamStats>& tiers) {
            py::list out;
            for (const StreamStats& t : tiers) out.append(py::make_tuple(t.blocks, t.bytes, t.items, t.extra));
            return out;
        };
        py::list nodes;
        for (const auto& tiers : s.node_streams) nodes.append(rows(tiers));
        d["node_streams"] = nodes;
        d["triangle_streams"] = rows(s.triangle_streams);
        d["kd_build_ms"] = s.kd_build_ms;
        d["emit_ms"] = s.emit_ms;
        d["max_depth"] = s.max_depth;
        d["emission_jobs"] = s.emission_jobs;
        return d;
    }

private:
    static std::uint64_t checked_offset(std::uint64_t offset) {
        if (offset == 0 || offset % writer::DirectAppender::kAlign) {
            throw std::invalid_argument("output_offset: a multiple of 4096 past the header and the index");
        }
        return offset;
    }

    writer::ModelBlocks blocks_;  // declared first: the writer's sink writes into it
    std::unique_ptr<ModelWriter> writer_;
};

std::shared_ptr<Scene> decode(const py::list& blocks, const std::vector<std::uint32_t>& stream_first,
                              const std::vector<double>& centre, const std::vector<double>& lo,
                              const std::vector<double>& hi, std::uint64_t triangle_ids, bool has_colours,
                              bool quantized_splits, bool quantized_vertices, std::uint32_t tier_count, bool tiered,
                              bool compact_triangles, bool packed_treelets, bool voxel_errors) {
    DecodeInput in;
    std::vector<std::string_view> views;
    for (const py::handle& b : blocks) {
        const std::string_view v = b.cast<py::bytes>();
        in.blocks.push_back(reinterpret_cast<const std::uint8_t*>(v.data()));
        in.sizes.push_back(v.size());
    }
    in.stream_first = stream_first;
    in.tier_count = tier_count;
    in.tiered = tiered;
    if (centre.size() != 3) throw std::invalid_argument("centre must have three components");
    in.centre = {centre[0], centre[1], centre[2]};
    in.root_cell = to_box(lo, hi);
    in.triangle_ids = triangle_ids;
    in.has_colours = has_colours;
    in.quantized_splits = quantized_splits;
    in.packed_treelets = packed_treelets;
    if (packed_treelets && !quantized_splits) throw std::invalid_argument("packed treelets need quantized splits");
    in.voxel_errors = voxel_errors;
    if (voxel_errors && !quantized_splits) throw std::invalid_argument("voxel errors need quantized splits");
    in.quantized_vertices = quantized_vertices;
    in.compact_triangles = compact_triangles;
    for (std::uint32_t f : stream_first) {
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

// FLAG_QUANTIZED_VERTICES: moves every corner of a chunk of records (nine f32 first) to
// the nearest point of the vertex grid of the root cell [lo, hi] (format.h), kept inside
// the cell so the tree's root still holds every triangle. Done before the tree is built,
// so the tree and its voxels are exact for the triangles as stored.
void snap_to_vertex_grid(const py::buffer& records, const std::vector<double>& lo, const std::vector<double>& hi) {
    // In place, so never through a converted copy.
    const py::buffer_info buf = records.request(true);
    if (buf.ndim != 2 || buf.itemsize != 1 || buf.shape[1] < 36 || buf.strides[1] != 1 || buf.strides[0] != buf.shape[1]) {
        throw std::invalid_argument("records: a writeable, contiguous (n, stride) uint8 array");
    }
    const Box3f cell = to_box(lo, hi);
    const Vec3f steps = format::vertex_grid_steps(cell.lo, cell.hi);
    float k_lo[3], k_hi[3];
    for (int a = 0; a < 3; ++a) {
        k_lo[a] = std::ceil(cell.lo[a] / steps[a]);
        k_hi[a] = std::floor(cell.hi[a] / steps[a]);
    }
    const std::size_t n = static_cast<std::size_t>(buf.shape[0]), stride = static_cast<std::size_t>(buf.shape[1]);
    std::uint8_t* data = static_cast<std::uint8_t*>(buf.ptr);
    py::gil_scoped_release release;
    ThreadPool::global().parallel_for((n + 65535) / 65536, [&](std::size_t b, unsigned) {
        for (std::size_t i = b * 65536; i < std::min(n, (b + 1) * 65536); ++i) {
            float f[9];
            std::memcpy(f, data + i * stride, 36);
            for (int c = 0; c < 9; ++c) {
                const int a = c % 3;
                const float k = std::clamp(std::nearbyint(f[c] / steps[a]), k_lo[a], k_hi[a]);
                f[c] = format::grid_vertex(static_cast<std::int32_t>(k), steps[a]);
            }
            std::memcpy(data + i * stride, f, 36);
        }
    });
}

// The read phase's records: per triangle its corners as float32(vertex - centre), computed
// in double as the in-core Scene does (bit-identical vertices on both paths), the u32 input
// id and, when given, the u32 0x00BBGGRR colour. Triangles whose float32 corners span no
// area are left out, as the kd build would, and counted. Runs on the pool, block by block:
// each block writes its records where its triangles would go and the blocks then close
// up, so the kept records are in input order at the start of the destination.
struct Records {
    std::size_t kept = 0, dropped = 0;
    float lo[3], hi[3];
    std::int64_t bad = -1;  // the first triangle whose corner fetch failed (a bad index)
};

template <typename Corners>
Records make_records_core(std::size_t n, const Corners& corners, const std::uint8_t* colours, std::size_t colour_stride,
                          const std::uint32_t* ids, std::uint64_t first_id, const double centre[3], std::uint8_t* dst,
                          unsigned lanes) {
    const std::size_t stride = 36 + 4 + (colours != nullptr ? 4 : 0);
    constexpr std::size_t kBlock = 1 << 15;
    const std::size_t blocks = (n + kBlock - 1) / kBlock;
    std::vector<Records> parts(blocks);
    ThreadPool::global().parallel_for(blocks, [&](std::size_t b, unsigned) {
        Records& r = parts[b];
        const std::size_t begin = b * kBlock, end = std::min(n, begin + kBlock);
        std::uint8_t* out = dst + begin * stride;
        __m128 lo = _mm_set1_ps(std::numeric_limits<float>::infinity()), hi = _mm_sub_ps(_mm_setzero_ps(), lo);
        for (std::size_t i = begin; i < end; ++i) {
            double v[9];
            if (!corners(i, v)) {
                r.bad = static_cast<std::int64_t>(i);
                return;
            }
            float f[12] = {};
            for (int k = 0; k < 9; ++k) f[k] = static_cast<float>(v[k] - centre[k % 3]);
            if (!has_area(Vec3f(f[0], f[1], f[2]), Vec3f(f[3], f[4], f[5]), Vec3f(f[6], f[7], f[8]))) {
                ++r.dropped;
                continue;
            }
            std::memcpy(out, f, 36);
            const auto id = ids != nullptr ? ids[i] : static_cast<std::uint32_t>(first_id + i);
            std::memcpy(out + 36, &id, 4);
            if (colours != nullptr) {
                const std::uint8_t* c = colours + colour_stride * i;
                const std::uint32_t packed = static_cast<std::uint32_t>(c[0]) | (static_cast<std::uint32_t>(c[1]) << 8) |
                                             (static_cast<std::uint32_t>(c[2]) << 16);
                std::memcpy(out + 40, &packed, 4);
            }
            for (int k = 0; k < 9; k += 3) {  // lane 3 holds the next corner's x or 0: unused
                const __m128 p = _mm_loadu_ps(f + k);
                lo = _mm_min_ps(lo, p);
                hi = _mm_max_ps(hi, p);
            }
            out += stride;
            ++r.kept;
        }
        alignas(16) float l[4], h[4];
        _mm_store_ps(l, lo);
        _mm_store_ps(h, hi);
        for (int k = 0; k < 3; ++k) r.lo[k] = l[k], r.hi[k] = h[k];
    }, lanes);
    Records all;
    for (int k = 0; k < 3; ++k) {
        all.lo[k] = std::numeric_limits<float>::infinity();
        all.hi[k] = -std::numeric_limits<float>::infinity();
    }
    std::size_t at = 0;
    for (std::size_t b = 0; b < blocks; ++b) {
        const Records& r = parts[b];
        if (r.bad >= 0) {
            all.bad = r.bad;
            return all;
        }
        if (at != b * kBlock && r.kept) std::memmove(dst + at * stride, dst + b * kBlock * stride, r.kept * stride);
        at += r.kept;
        all.kept += r.kept;
        all.dropped += r.dropped;
        for (int k = 0; k < 3; ++k) {
            all.lo[k] = std::min(all.lo[k], r.lo[k]);
            all.hi[k] = std::max(all.hi[k], r.hi[k]);
        }
    }
    return all;
}

using ByteArray = py::array_t<std::uint8_t, py::array::c_style>;

// Options every record call takes: colours ((n, 3) uint8, rows may be strided), explicit
// ids, the centre, and where the records go (`out`: at least n rows of the record size;
// none: a new array).
struct RecordOptions {
    py::array_t<std::uint32_t, py::array::c_style | py::array::forcecast> id_array;
    py::array rgb;
    const std::uint8_t* colours = nullptr;
    std::size_t colour_stride = 3;
    const std::uint32_t* ids = nullptr;
    double centre[3];
    ByteArray out;
    std::size_t stride;

    RecordOptions(const py::object& colours_, const py::object& ids_, const std::vector<double>& centre_, std::size_t n,
                  const py::object& out_) {
        if (centre_.size() != 3) throw std::invalid_argument("centre must have three components");
        for (int k = 0; k < 3; ++k) centre[k] = centre_[static_cast<std::size_t>(k)];
        if (!colours_.is_none()) {
            rgb = py::array::ensure(colours_);
            if (!rgb || rgb.dtype().kind() != 'u' || rgb.itemsize() != 1 || rgb.ndim() != 2 ||
                static_cast<std::size_t>(rgb.shape(0)) != n || rgb.shape(1) != 3 || rgb.strides(1) != 1) {
                throw std::invalid_argument("colours must be (n, 3) uint8 with contiguous rows");
            }
            colours = static_cast<const std::uint8_t*>(rgb.data());
            colour_stride = static_cast<std::size_t>(rgb.strides(0));
        }
        if (!ids_.is_none()) {
            id_array = decltype(id_array)::ensure(ids_);
            if (!id_array || static_cast<std::size_t>(id_array.size()) != n) throw std::invalid_argument("ids must be one uint32 per triangle");
            ids = id_array.data();
        }
        stride = record_size(colours != nullptr);
        if (out_.is_none()) {
            out = ByteArray({static_cast<py::ssize_t>(n), static_cast<py::ssize_t>(stride)});
        } else {
            out = out_.cast<ByteArray>();
            if (out.ndim() != 2 || static_cast<std::size_t>(out.shape(1)) != stride || static_cast<std::size_t>(out.shape(0)) < n ||
                !out.writeable()) {
                throw std::invalid_argument("out must be a writeable (>= n, record size) uint8 array");
            }
        }
    }
    std::uint8_t* dst() { return out.mutable_data(); }
};

// (records: the first `kept` rows of the destination, dropped, lo, hi, bad triangle or -1)
py::tuple records_result(const Records& r, RecordOptions& o) {
    py::object rows = o.out[py::slice(0, static_cast<py::ssize_t>(r.bad >= 0 ? 0 : r.kept), 1)];
    return py::make_tuple(rows, r.dropped, std::vector<float>(r.lo, r.lo + 3), std::vector<float>(r.hi, r.hi + 3), r.bad);
}

// Records from corners: (n, 3, 3) float64.
py::tuple make_records(DoubleArray corners, py::object colours, py::object ids, std::uint64_t first_id,
                       const std::vector<double>& centre, py::object out, unsigned threads) {
    if (corners.size() % 9 != 0) throw std::invalid_argument("corners must be (n, 3, 3)");
    const auto n = static_cast<std::size_t>(corners.size() / 9);
    RecordOptions o(colours, ids, centre, n, out);
    const double* c = corners.data();
    std::uint8_t* dst = o.dst();
    Records r;
    {
        py::gil_scoped_release release;
        r = make_records_core(
            n, [c](std::size_t i, double* v) { std::memcpy(v, c + 9 * i, 9 * sizeof(double)); return true; },
            o.colours, o.colour_stride, o.ids, first_id, o.centre, dst, threads);
    }
    return records_result(r, o);
}

// Vertex indices (n, 3) of any integer type and layout (a field of a face record array),
// read as int64.
struct Indices {
    const std::uint8_t* base;
    std::ptrdiff_t row, col;
    char kind;
    std::size_t size;

    explicit Indices(const py::array& a) {
        if (a.ndim() != 2 || a.shape(1) != 3) throw std::invalid_argument("indices must be (n, 3)");
        kind = a.dtype().kind();
        size = static_cast<std::size_t>(a.itemsize());
        if ((kind != 'i' && kind != 'u') || (size != 1 && size != 2 && size != 4 && size != 8)) {
            throw std::invalid_argument("indices must be integers");
        }
        if (a.dtype().byteorder() == '>') throw std::invalid_argument("indices must be in native byte order");
        base = static_cast<const std::uint8_t*>(a.data());
        row = a.strides(0);
        col = a.strides(1);
    }
    std::int64_t operator()(std::size_t i, int c) const {
        const std::uint8_t* p = base + static_cast<std::ptrdiff_t>(i) * row + c * col;
        switch (size) {
            case 1: return kind == 'i' ? static_cast<std::int8_t>(*p) : *p;
            case 2: return kind == 'i' ? load_as<std::int16_t>(p) : load_as<std::uint16_t>(p);
            case 4: return kind == 'i' ? load_as<std::int32_t>(p) : load_as<std::uint32_t>(p);
            default: {
                std::uint64_t u;
                std::memcpy(&u, p, sizeof u);
                const bool fits = kind == 'i' || u <= static_cast<std::uint64_t>(std::numeric_limits<std::int64_t>::max());
                return fits ? static_cast<std::int64_t>(u) : std::int64_t{-1};
            }
        }
    }
    template <typename T>
    static std::int64_t load_as(const std::uint8_t* p) {
        T v;
        std::memcpy(&v, p, sizeof v);
        return static_cast<std::int64_t>(v);
    }
};

// A table of vertex records: `count` records of `stride` bytes, coordinate k at byte
// offsets[k], typed types[k] ("<f4", ">f4", "<f8", ">f8"): a binary PLY's vertex element
// where it lies in the file, or a staged float64 table.
struct VertexRecords {
    py::buffer_info buffer;
    const std::uint8_t* base;
    std::size_t stride, count, offsets[3];
    bool swap[3], wide[3];
    bool packed;  // native-order x, y, z side by side, all one width

    VertexRecords(const py::buffer& vertices, std::size_t stride_, const std::array<std::size_t, 3>& offsets_,
                  const std::array<std::string, 3>& types, std::size_t count_)
        : buffer(vertices.request()), stride(stride_), count(count_) {
        if (buffer.itemsize != 1 || static_cast<std::size_t>(buffer.size) < count * stride) {
            throw std::invalid_argument("vertices: a byte buffer of count * stride bytes");
        }
        base = static_cast<const std::uint8_t*>(buffer.ptr);
        for (int k = 0; k < 3; ++k) {
            const std::string& t = types[static_cast<std::size_t>(k)];
            if (t.size() != 3 || (t[0] != '<' && t[0] != '>') || t[1] != 'f' || (t[2] != '4' && t[2] != '8')) {
                throw std::invalid_argument("vertex coordinate types are <f4, >f4, <f8 or >f8");
            }
            wide[k] = t[2] == '8';
            swap[k] = t[0] == '>';
            offsets[k] = offsets_[static_cast<std::size_t>(k)];
            if (offsets[k] + (wide[k] ? 8 : 4) > stride) throw std::invalid_argument("vertex field past its record");
        }
        const std::size_t width = wide[0] ? 8 : 4;
        packed = offsets[1] == offsets[0] + width && offsets[2] == offsets[1] + width && wide[0] == wide[1] &&
                 wide[1] == wide[2] && !swap[0] && !swap[1] && !swap[2];
    }

    double coord(const std::uint8_t* rec, int k) const {
        std::uint8_t b[8];
        const std::size_t w = wide[k] ? 8 : 4;
        std::memcpy(b, rec + offsets[k], w);
        if (swap[k]) std::reverse(b, b + w);
        if (wide[k]) {
            double d;
            std::memcpy(&d, b, 8);
            return d;
        }
        float f;
        std::memcpy(&f, b, 4);
        return f;
    }

    // Calls fn(fetch) with a fetch(vertex index, double* xyz) specialised for the layout:
    // the common ones get their own loops, anything else goes coordinate by coordinate.
    template <typename Fn>
    auto with_fetch(Fn&& fn) const {
        const std::size_t at = offsets[0];
        if (packed && !wide[0]) {
            return fn([this, at](std::size_t j, double* v) {
                float f[3];
                std::memcpy(f, base + j * stride + at, sizeof f);
                v[0] = f[0], v[1] = f[1], v[2] = f[2];
            });
        }
        if (packed) {
            return fn([this, at](std::size_t j, double* v) { std::memcpy(v, base + j * stride + at, 3 * sizeof(double)); });
        }
        return fn([this](std::size_t j, double* v) {
            for (int k = 0; k < 3; ++k) v[k] = coord(base + j * stride, k);
        });
    }
};

// Records from vertex indices into a table of vertex records (see VertexRecords). The
// result's last field names the first triangle with an index outside 0 ... count - 1
// (-1: none), and then no records are made.
py::tuple make_indexed_records(const py::buffer& vertices, std::size_t stride, const std::array<std::size_t, 3>& offsets,
                               const std::array<std::string, 3>& types, std::size_t count, const py::array& indices,
                               py::object colours, py::object ids, std::uint64_t first_id,
                               const std::vector<double>& centre, py::object out, unsigned threads) {
    const VertexRecords table(vertices, stride, offsets, types, count);
    const Indices idx(indices);
    const auto n = static_cast<std::size_t>(indices.shape(0));
    RecordOptions o(colours, ids, centre, n, out);
    std::uint8_t* dst = o.dst();
    Records r;
    {
        py::gil_scoped_release release;
        r = table.with_fetch([&](auto&& fetch) {
            return make_records_core(
                n,
                [&](std::size_t i, double* v) {
                    for (int c = 0; c < 3; ++c) {
                        const std::int64_t j = idx(i, c);
                        if (j < 0 || static_cast<std::uint64_t>(j) >= count) return false;
                        fetch(static_cast<std::size_t>(j), v + 3 * c);
                    }
                    return true;
                },
                o.colours, o.colour_stride, o.ids, first_id, o.centre, dst, threads);
        });
    }
    return records_result(r, o);
}

// (lo, hi, first vertex with a non-finite coordinate or -1) of a table of vertex records,
// on the pool: what the model centre and the root cell come from.
py::tuple vertex_bounds(const py::buffer& vertices, std::size_t stride, const std::array<std::size_t, 3>& offsets,
                        const std::array<std::string, 3>& types, std::size_t count, unsigned threads) {
    const VertexRecords table(vertices, stride, offsets, types, count);
    constexpr std::size_t kBlock = 1 << 16;
    const std::size_t blocks = (count + kBlock - 1) / kBlock;
    struct Part {
        double lo[3], hi[3];
        std::int64_t bad = -1;
    };
    std::vector<Part> parts(blocks);
    {
        py::gil_scoped_release release;
        table.with_fetch([&](auto&& fetch) {
            ThreadPool::global().parallel_for(blocks, [&](std::size_t b, unsigned) {
                Part& p = parts[b];
                for (int k = 0; k < 3; ++k) {
                    p.lo[k] = std::numeric_limits<double>::infinity();
                    p.hi[k] = -std::numeric_limits<double>::infinity();
                }
                const std::size_t end = std::min(count, (b + 1) * kBlock);
                for (std::size_t j = b * kBlock; j < end; ++j) {
                    double v[3];
                    fetch(j, v);
                    if (!std::isfinite(v[0]) || !std::isfinite(v[1]) || !std::isfinite(v[2])) {
                        p.bad = static_cast<std::int64_t>(j);
                        return;
                    }
                    for (int k = 0; k < 3; ++k) {
                        p.lo[k] = std::min(p.lo[k], v[k]);
                        p.hi[k] = std::max(p.hi[k], v[k]);
                    }
                }
            }, threads);
            return 0;
        });
    }
    std::vector<double> lo(3, std::numeric_limits<double>::infinity()), hi(3, -std::numeric_limits<double>::infinity());
    for (const Part& p : parts) {
        if (p.bad >= 0) return py::make_tuple(lo, hi, p.bad);
        for (int k = 0; k < 3; ++k) {
            lo[static_cast<std::size_t>(k)] = std::min(lo[static_cast<std::size_t>(k)], p.lo[k]);
            hi[static_cast<std::size_t>(k)] = std::max(hi[static_cast<std::size_t>(k)], p.hi[k]);
        }
    }
    return py::make_tuple(lo, hi, -1);
}

}  // namespace

void bind_model(py::module_& m) {
    py::class_<PyModelWriter>(m, "ModelWriter",
                              "Writes kd-subtrees as treelets, voxels and triangle blocks into the model file `output`, "
                              "from output_offset on, past the page cache (vastray/model_assembly.py finishes the file)")
        .def(py::init<bool, const std::string&, std::uint64_t, py::object, int, float, float, float, int, int, unsigned,
                      bool, py::object, double, int, py::object, bool, bool, bool, int, bool, float>(),
             py::arg("has_colours"), py::arg("output"), py::arg("output_offset"), py::arg("progress") = py::none(),
             py::arg("leaf_size") = 4, py::arg("traversal_cost") = 1.0f, py::arg("intersection_cost") = 1.5f,
             py::arg("empty_space_ratio") = 0.15f, py::arg("bins") = 32, py::arg("voxel_rays") = 3,
             py::arg("threads") = 0u, py::arg("quantized_splits") = false,
             py::arg("vertex_steps") = py::none(), py::arg("tier_width") = 0.0, py::arg("tier_coarse_octaves") = 4,
             py::arg("root_cell") = py::none(), py::arg("compact_triangles") = false, py::arg("packed_voxels") = true,
             py::arg("packed_treelets") = true, py::arg("lz4_hc_level") = 0, py::arg("voxel_errors") = false,
             py::arg("voxel_error_floor") = 0.5f)
        .def("add_subtree", &PyModelWriter::add_subtree, py::arg("records"), py::arg("lo"), py::arg("hi"),
             py::arg("level"), py::arg("lod_parent") = py::none())
        .def("add_inner_treelet", &PyModelWriter::add_inner_treelet, py::arg("level"), py::arg("lo"), py::arg("hi"),
             py::arg("axes"), py::arg("splits"), py::arg("children"))
        .def("finish", &PyModelWriter::finish, py::arg("root"))
        .def_property_readonly("levels", &PyModelWriter::levels)
        .def_property_readonly("output", &PyModelWriter::output)
        .def_property_readonly("stats", &PyModelWriter::stats);
    m.def("make_records", &make_records, py::arg("corners"), py::arg("colours"), py::arg("ids"), py::arg("first_id"),
          py::arg("centre"), py::arg("out") = py::none(), py::arg("threads") = 0u,
          "Builder records for a chunk of triangles (corners), zero-area ones left out");
    m.def("make_indexed_records", &make_indexed_records, py::arg("vertices"), py::arg("stride"), py::arg("offsets"),
          py::arg("types"), py::arg("count"), py::arg("indices"), py::arg("colours"), py::arg("ids"),
          py::arg("first_id"), py::arg("centre"), py::arg("out") = py::none(), py::arg("threads") = 0u,
          "Builder records for a chunk of indexed triangles, gathered from vertex records");
    m.def("vertex_bounds", &vertex_bounds, py::arg("vertices"), py::arg("stride"), py::arg("offsets"), py::arg("types"),
          py::arg("count"), py::arg("threads") = 0u, "Bounds of a table of vertex records, and its first non-finite vertex");
    m.def("snap_to_vertex_grid", &snap_to_vertex_grid, py::arg("records"), py::arg("lo"), py::arg("hi"),
          "Moves the corners of builder records onto the quantized vertex grid of the root cell [lo, hi]");
    m.def(
        "vertex_grid_steps",
        [](const std::vector<double>& lo, const std::vector<double>& hi) {
            const Vec3f s = format::vertex_grid_steps(to_box(lo, hi).lo, to_box(lo, hi).hi);
            return py::make_tuple(s.x, s.y, s.z);
        },
        py::arg("lo"), py::arg("hi"), "The quantized vertex grid's step on each axis for the root cell [lo, hi]");
    bind_ingest(m);
    m.def("sift8", &sift8, py::arg("records"), py::arg("axes"), py::arg("splits"), py::arg("cell_lo"),
          py::arg("cell_hi"), "One chunk of an out-of-core split pass: records per cell and cell bounds");
    m.def("decode_model", &decode, py::arg("blocks"), py::arg("stream_first"), py::arg("centre"), py::arg("lo"),
          py::arg("hi"), py::arg("triangle_ids"), py::arg("has_colours"), py::arg("quantized_splits") = false,
          py::arg("quantized_vertices") = false, py::arg("tier_count") = 1u, py::arg("tiered") = false,
          py::arg("compact_triangles") = false, py::arg("packed_treelets") = false, py::arg("voxel_errors") = false,
          "Decode a whole model (raw blocks by global id; the first block of each stream, level-major) into an "
          "in-core Scene");
}
