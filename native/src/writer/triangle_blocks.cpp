#include "writer/triangle_blocks.h"

#include <cstring>

namespace vastray::writer {

using format::kBlockSize;

std::pair<std::uint32_t, std::uint32_t> TriangleBlocks::add_leaf(const std::uint32_t* tris, std::uint32_t count,
                                                                 const TriangleSource& src) {
    constexpr std::uint32_t kWhole = 4096;
    if (count <= kWhole) {
        const std::size_t list0 = list_.size(), tri0 = ids_.size(), vert0 = verts_.size();
        if (insert(tris, count, src) && layout().end <= kBlockSize) return {blocks_, static_cast<std::uint32_t>(list0)};
        // Too full: close the block as it was before this leaf and try a fresh one.
        truncate(list0, tri0, vert0);
        flush();
        if (insert(tris, count, src) && layout().end <= kBlockSize) return {blocks_, 0};
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
        if (!insert(tris + i, 1, src)) throw std::logic_error("a triangle does not fit in an empty triangle block");
    }
    return {start, 0};
}

void TriangleBlocks::truncate(std::size_t list_size, std::size_t tris, std::size_t verts) {
    list_.resize(list_size);
    ids_.resize(tris);
    tri_verts_.resize(3 * tris);
    if (has_colours_) colours_.resize(tris);
    verts_.resize(verts);
}

void TriangleBlocks::flush() {
    if (list_.empty()) return;
    const format::TriangleBlockLayout l = layout();
    std::vector<std::uint8_t> bytes(l.end, 0);
    const std::uint32_t header[4] = {static_cast<std::uint32_t>(list_.size()), static_cast<std::uint32_t>(ids_.size()),
                                     static_cast<std::uint32_t>(verts_.size()), 0};
    std::memcpy(bytes.data(), header, sizeof header);
    std::memcpy(bytes.data() + l.list, list_.data(), 2 * list_.size());
    std::memcpy(bytes.data() + l.triangles, tri_verts_.data(), 2 * tri_verts_.size());
    std::memcpy(bytes.data() + l.ids, ids_.data(), 4 * ids_.size());
    if (has_colours_) std::memcpy(bytes.data() + l.colours, colours_.data(), 4 * colours_.size());
    std::memcpy(bytes.data() + l.vertices, verts_.data(), 12 * verts_.size());
    stats_.stored_triangles += ids_.size();
    stats_.stored_vertices += verts_.size();
    stats_.triangle_blocks++;
    stats_.triangle_bytes += bytes.size();
    out_(-1, store_block(bytes));
    ++blocks_;
    list_.clear();
    ids_.clear();
    tri_verts_.clear();
    colours_.clear();
    verts_.clear();
    id_map_.clear();
    vertex_map_.clear();
}

bool TriangleBlocks::insert(const std::uint32_t* tris, std::uint32_t count, const TriangleSource& src) {
    for (std::uint32_t i = 0; i < count; ++i) {
        // Past these counts no block can hold what is inserted (a vertex takes 12 bytes,
        // a triangle at least 12): stop before the dedup tables fill.
        if (verts_.size() > kMaxVertices || ids_.size() > kMaxTriangles) return false;
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
                const VertexKey key{{format::float_bits(p.x), format::float_bits(p.y), format::float_bits(p.z)}};
                bool new_vertex = false;
                const std::uint32_t v = vertex_map_.find_or_insert(key, static_cast<std::uint32_t>(verts_.size()), new_vertex);
                if (new_vertex) verts_.push_back(p);
                tri_verts_.push_back(static_cast<std::uint16_t>(v));
            }
        }
        list_.push_back(static_cast<std::uint16_t>(local));
    }
    return true;
}

}  // namespace vastray::writer
