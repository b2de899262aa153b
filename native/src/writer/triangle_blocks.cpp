#include "writer/triangle_blocks.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

#include "writer/treelet.h"

namespace vastray::writer {

using format::kBlockSize;

std::pair<std::uint32_t, std::uint32_t> TriangleBlocks::add_leaf(const std::uint32_t* tris, std::uint32_t count,
                                                                 const TriangleSource& src) {
    constexpr std::uint32_t kWhole = 4096;
    if (count <= kWhole) {
        const std::size_t list0 = list_.size(), tri0 = ids_.size(), vert0 = verts_.size();
        if (insert(tris, count, src) && layout().end <= kBlockSize) {
            open_leaves_.push_back({static_cast<std::uint32_t>(list0), tris, count});
            return {blocks_, static_cast<std::uint32_t>(list0)};
        }
        // Too full: close the block as it was before this leaf and try a fresh one.
        truncate(list0, tri0, vert0);
        flush();
        if (insert(tris, count, src) && layout().end <= kBlockSize) {
            open_leaves_.push_back({0, tris, count});
            return {blocks_, 0};
        }
        truncate(0, 0, 0);
        id_map_.clear();
        vertex_map_.clear();
    } else {
        flush();
    }
    // Worst case for one more triangle: list entry, record, id, colour, 3 vertices.
    constexpr std::size_t kWorst = 2 + 6 + 4 + 4 + 36 + 8;
    const std::uint32_t start = blocks_;
    for (std::uint32_t i = 0; i < count; ++i) {
        if (layout().end + kWorst > kBlockSize) flush();
        const std::size_t list0 = list_.size(), tri0 = ids_.size(), vert0 = verts_.size();
        if (insert(tris + i, 1, src) && layout().end <= kBlockSize) continue;
        // Quantized vertices: a vertex far from the others turned the block to f32.
        truncate(list0, tri0, vert0);
        flush();
        if (!insert(tris + i, 1, src)) throw std::logic_error("a triangle does not fit in an empty triangle block");
    }
    open_continues_ = true;
    return {start, 0};
}

bool TriangleBlocks::take_open_leaves(std::vector<OpenLeaf>& out) {
    if (list_.empty()) return false;
    if (open_continues_) {
        flush();
        return false;
    }
    out = std::move(open_leaves_);
    clear_open();
    return true;
}

void TriangleBlocks::truncate(std::size_t list_size, std::size_t tris, std::size_t verts) {
    list_.resize(list_size);
    ids_.resize(tris);
    tri_verts_.resize(3 * tris);
    if (has_colours_) colours_.resize(tris);
    verts_.resize(verts);
    if (quantized_) {
        grid_.resize(verts);
        reset_span();
        for (const auto& k : grid_) extend_span(k);
    }
}

void TriangleBlocks::reset_span() {
    k_lo_.fill(std::numeric_limits<std::int32_t>::max());
    k_hi_.fill(std::numeric_limits<std::int32_t>::min());
}

void TriangleBlocks::extend_span(const std::array<std::int32_t, 3>& k) {
    for (int a = 0; a < 3; ++a) {
        k_lo_[a] = std::min(k_lo_[a], k[a]);
        k_hi_[a] = std::max(k_hi_[a], k[a]);
    }
}

void TriangleBlocks::flush() {
    if (list_.empty()) return;
    const format::TriangleBlockLayout l = layout();
    std::vector<std::uint8_t> bytes(l.end, 0);
    const std::uint32_t header[4] = {static_cast<std::uint32_t>(list_.size()), static_cast<std::uint32_t>(ids_.size()),
                                     static_cast<std::uint32_t>(verts_.size()), packing()};
    std::memcpy(bytes.data(), header, sizeof header);
    std::memcpy(bytes.data() + l.list, list_.data(), 2 * list_.size());
    std::memcpy(bytes.data() + l.triangles, tri_verts_.data(), 2 * tri_verts_.size());
    std::memcpy(bytes.data() + l.ids, ids_.data(), 4 * ids_.size());
    if (has_colours_) std::memcpy(bytes.data() + l.colours, colours_.data(), 4 * colours_.size());
    if (l.packed) {
        std::memcpy(bytes.data() + l.vertices, k_lo_.data(), 12);
        std::uint8_t* at = bytes.data() + l.vertices + 12;
        for (const auto& k : grid_) {
            std::uint64_t w = 0;
            std::uint32_t shift = 0;
            for (int a = 0; a < 3; ++a) {
                w |= static_cast<std::uint64_t>(static_cast<std::uint32_t>(k[a] - k_lo_[a])) << shift;
                shift += l.bits[a];
            }
            std::memcpy(at, &w, l.record);
            at += l.record;
        }
        stats_.vertex_bytes += l.end - l.vertices;
    } else {
        std::memcpy(bytes.data() + l.vertices, verts_.data(), 12 * verts_.size());
        stats_.vertex_bytes += 12 * verts_.size();
    }
    stats_.stored_triangles += ids_.size();
    stats_.stored_vertices += verts_.size();
    stats_.triangle_blocks++;
    stats_.triangle_bytes += bytes.size();
    StreamStats& stream = triangle_stream(stats_, tier_);
    stream.blocks++;
    stream.bytes += bytes.size();
    stream.items += ids_.size();
    stream.extra += verts_.size();
    out_(-1, tier_, store_block(bytes));
    ++blocks_;
    clear_open();
}

void TriangleBlocks::clear_open() {
    list_.clear();
    ids_.clear();
    tri_verts_.clear();
    colours_.clear();
    verts_.clear();
    grid_.clear();
    reset_span();
    id_map_.clear();
    vertex_map_.clear();
    open_leaves_.clear();
    open_continues_ = false;
}

std::array<std::int32_t, 3> TriangleBlocks::grid_index(const Vec3f& p) const {
    std::array<std::int32_t, 3> k;
    for (int a = 0; a < 3; ++a) {
        const float q = p[a] / steps_[a];  // exact: the step is a power of two
        constexpr float kMax = static_cast<float>(1 << format::kVertexGridBits);
        if (!(std::abs(q) < kMax) || std::nearbyint(q) != q) {
            throw std::logic_error("a vertex is not on the quantized vertex grid");
        }
        k[a] = static_cast<std::int32_t>(q);
    }
    return k;
}

bool TriangleBlocks::insert(const std::uint32_t* tris, std::uint32_t count, const TriangleSource& src) {
    for (std::uint32_t i = 0; i < count; ++i) {
        // Past these counts no block can hold what is inserted (a vertex takes 12 bytes,
        // a triangle at least 12): stop before the dedup tables fill.
        if (verts_.size() > max_vertices_ || ids_.size() > kMaxTriangles) return false;
        const std::uint32_t t = tris[i];
        bool fresh = false;
        const std::uint32_t id = src.id(t);
        const std::uint32_t local = id_map_.find_or_insert(id, static_cast<std::uint32_t>(ids_.size()), fresh);
        if (fresh) {
            ids_.push_back(id);
            if (has_colours_) colours_.push_back(src.colour(t));
            const Vec3f* corners = src.corners(t);
            for (int k = 0; k < 3; ++k) {
                const Vec3f& p = corners[k];
                // Quantized: one vertex per grid point (+0 and -0 alike).
                std::array<std::int32_t, 3> g{};
                if (quantized_) g = grid_index(p);
                const VertexKey key = quantized_
                    ? VertexKey{{static_cast<std::uint32_t>(g[0]), static_cast<std::uint32_t>(g[1]), static_cast<std::uint32_t>(g[2])}}
                    : VertexKey{{format::float_bits(p.x), format::float_bits(p.y), format::float_bits(p.z)}};
                bool new_vertex = false;
                const std::uint32_t v = vertex_map_.find_or_insert(key, static_cast<std::uint32_t>(verts_.size()), new_vertex);
                if (new_vertex) {
                    if (quantized_) {
                        // Stored as k * step, the value every reader decodes (f32 blocks too).
                        verts_.push_back({format::grid_vertex(g[0], steps_.x), format::grid_vertex(g[1], steps_.y),
                                          format::grid_vertex(g[2], steps_.z)});
                        grid_.push_back(g);
                        extend_span(g);
                    } else {
                        verts_.push_back(p);
                    }
                }
                tri_verts_.push_back(static_cast<std::uint16_t>(v));
            }
        }
        list_.push_back(static_cast<std::uint16_t>(local));
    }
    return true;
}

}  // namespace vastray::writer
