// Ray traversal of a built model straight from its cached blocks, with level of detail
// (paper 000 Algorithm 1). The walk is the in-core kd traversal (traverse.h), step for
// step, over the on-disk node layout (format.h), plus two ways to stop early at a LOD
// node's voxel:
//   - the LOD test: the voxel's enclosing-sphere radius R is small enough for the ray's
//     footprint, R <= (cone_t0 + t_entry) * cone (PoE metric for primary and shadow rays,
//     solid-angle metric for AO rays: both are cones from a ray origin);
//   - missing data: a child treelet or triangle block that is not in the cache is
//     requested, and the ray hits the last voxel it passed instead. It never waits.
// With cone = 0 and every block present the answers equal the in-core traversal's.
#pragma once

#include <cstdint>
#include <cstring>
#include <utility>
#include <vector>

#include "vastray/block_cache.h"
#include "vastray/format.h"
#include "vastray/isa.h"
#include "vastray/traverse.h"

VASTRAY_KERNEL_BEGIN

constexpr std::uint32_t kVoxelPrim = 0xfffffffeu;  // LodHit::prim of a voxel hit

struct LodRay {
    Ray ray;
    float cone_t0 = 0;  // distance already covered by the cone before this ray's origin
    float cone = 0;     // LOD cone slope; 0 disables the LOD test (full detail)
};

struct LodHit : Hit {
    // Triangle hits: the triangle block and the triangle's index in it.
    const std::uint8_t* tri_block = nullptr;
    std::uint32_t local = 0;
    // Voxel hits: the sample for the face the ray entered, and the voxel's radius.
    std::uint32_t sample = 0;
    float voxel_radius = 0;
    int face = 0;
};

// One lane's view of a model during one frame: block lookups that stamp the working
// set, request what is missing and count what happened.
struct LodLane {
    BlockCache* cache = nullptr;
    CachedModel* model = nullptr;
    std::uint32_t tick = 0;
    const std::uint32_t* level_first = nullptr;
    std::uint32_t tri_level = 0, block_count = 0;
    bool has_colours = false;
    bool quantized_splits = false;  // FLAG_QUANTIZED_SPLITS: 4-byte basic nodes, splits on their cell's grid
    bool quantized_vertices = false;  // FLAG_QUANTIZED_VERTICES: bit-packed grid offsets in triangle blocks
    Vec3f vertex_steps{1, 1, 1};      // that grid's steps
    bool compact_triangles = false;   // FLAG_COMPACT_TRIANGLES: compact triangle blocks (format.h)
    std::vector<std::pair<CachedModel*, std::uint32_t>> requests;  // first requests
    std::uint64_t lookups = 0, hits = 0, missing = 0, bad = 0, ws_blocks = 0, ws_bytes = 0;
    std::uint64_t node_visits = 0, triangle_tests = 0, voxel_hits = 0;

    const std::uint8_t* lookup(std::uint32_t block, float priority) {
        ++lookups;
        const std::int32_t slot = model->slot(block);
        if (slot >= 0) {
            ++hits;
            if (cache->touch(slot, tick)) {
                ++ws_blocks;
                ws_bytes += cache->slot_raw_size(slot);
            }
            return cache->slot_data(slot);
        }
        ++missing;
        if (slot == CachedModel::kBad) {
            ++bad;
        } else if (model->request(block, priority)) {
            requests.emplace_back(model, block);
        }
        return nullptr;
    }
};

namespace lod_detail {

template <typename T>
inline T load(const std::uint8_t* p) {
    T v;
    std::memcpy(&v, p, sizeof v);
    return v;
}

// A voxel: its samples and enclosing radius.
// Voxel and NodeRef are plain aggregates on purpose: traversal stacks hold 64 of them,
// and default member initialisers would zero the whole stack for every ray.
struct Voxel {
    const std::uint8_t* samples;
    float radius;
};

inline void hit_voxel(const Voxel& v, int entry_axis, const Ray& ray, float t, LodHit& hit) {
    hit.t = t;
    hit.prim = kVoxelPrim;
    hit.tri_block = nullptr;
    hit.voxel_radius = v.radius;
    const int face = 2 * entry_axis + (ray.dir[entry_axis] >= 0.0f ? 0 : 1);
    hit.face = face;
    const std::uint32_t s0 = load<std::uint32_t>(v.samples);
    hit.sample = (s0 & format::kOneSample) ? s0 : load<std::uint32_t>(v.samples + 4 * face);
}

// A node in a cached block: the block's bytes, the node's offset, its LOD level, and its
// cell (a quantized model's basic nodes store their split as a step of it).
struct NodeRef {
    const std::uint8_t* block;
    std::uint32_t off, level;
    float lo[3], hi[3];
};

inline NodeRef root_ref(const std::uint8_t* block, const Box3f& cell) {
    return {block, 0, 0, {cell.lo.x, cell.lo.y, cell.lo.z}, {cell.hi.x, cell.hi.y, cell.hi.z}};
}

// An inner node's split position: word 1, or (a quantized model's basic node) the step
// of its cell on the split axis in word 0 (format.h).
inline float split_of(bool quantized, const NodeRef& node, std::uint32_t w) {
    if (quantized && !format::is_lod(w)) {
        const int a = std::min(format::axis_of(w), 2);
        return format::dequantize_split(node.lo[a], node.hi[a], format::basic_split_step(w));
    }
    return format::bits_float(load<std::uint32_t>(node.block + node.off + 4));
}

// A LOD node's voxel: its samples, and its radius (a quantized model derives it from the
// cell instead of storing it).
inline Voxel voxel_of(bool quantized, const NodeRef& node, std::uint32_t w) {
    const float radius =
        quantized ? format::cell_radius(Vec3f(node.hi[0] - node.lo[0], node.hi[1] - node.lo[1], node.hi[2] - node.lo[2]))
                  : format::bits_float(load<std::uint32_t>(node.block + node.off + 8));
    return {node.block + node.off + 4 * format::lod_voxel_off4(w), radius};
}

// The block holding a LOD node's child treelets, or null when it is not cached (then it
// is requested) or the node is damaged (points outside the next level).
inline const std::uint8_t* lod_child_block(LodLane& lane, const NodeRef& node, float priority) {
    if (node.level + 1 >= lane.tri_level) return nullptr;  // no node level below: damaged
    const std::uint32_t block = lane.level_first[node.level + 1] +
                                load<std::uint32_t>(node.block + node.off + format::lod_child_block_at(lane.quantized_splits));
    return block < lane.level_first[node.level + 2] ? lane.lookup(block, priority) : nullptr;
}

// An inner node's children (null block: empty child), with their cells split at
// `split`. `child` is the child block of a LOD node. False for a damaged node, whose
// offsets would loop or leave the block.
inline bool children_of(bool quantized, const NodeRef& node, std::uint32_t w, float split,
                        const std::uint8_t* child, NodeRef& left, NodeRef& right) {
    using namespace format;
    const bool has_l = (w & kLeftEmpty) == 0, has_r = (w & kRightEmpty) == 0;
    const int axis = std::min(axis_of(w), 2);
    left = right = node;
    left.hi[axis] = split;
    right.lo[axis] = split;
    left.block = right.block = nullptr;
    if (is_lod(w)) {
        const std::uint32_t first = 8 * lod_child_off8(w);
        left.level = right.level = node.level + 1;
        if (has_l) {
            left.block = child;
            left.off = first;
        }
        if (has_r) {
            right.block = child;
            right.off = has_l ? first + 8 * lod_right_from_left8(w) : first;
        }
    } else {
        // Basic nodes are 8 bytes, 4 in a quantized model; offsets count in their size.
        const std::uint32_t size = quantized ? 4 : 8;
        const std::uint32_t r = basic_right_off8(w);
        if (has_l && has_r && r < 2) return false;
        if (has_l) {
            left.block = node.block;
            left.off = node.off + size;
        }
        if (has_r) {
            right.block = node.block;
            right.off = has_l ? node.off + size * r : node.off + size;
        }
    }
    return !(left.block && left.off > kBlockSize - 8) && !(right.block && right.off > kBlockSize - 8);
}

// Root clip that also says through which face the ray enters (the axis of the largest
// near distance), for the shading of a voxel hit on the root's children.
inline bool clip_with_axis(const Ray& ray, const Box3f& box, float& t0, float& t1, int& axis) {
    if (!clip_ray_to_box(ray, box, t0, t1)) return false;
    axis = 0;
    float best = -std::numeric_limits<float>::infinity();
    for (int a = 0; a < 3; ++a) {
        if (ray.dir[a] == 0.0f) continue;
        const float tn = ((ray.dir[a] > 0 ? box.lo[a] : box.hi[a]) - ray.org[a]) / ray.dir[a];
        if (tn > best) {
            best = tn;
            axis = a;
        }
    }
    return true;
}

// Walks the triangles of one leaf: its run of list entries in a triangle block and, for
// leaves too big for one block, on into the following blocks. Entries that point
// outside their block are skipped; a block that is missing (requested) or has a
// damaged header ends the walk with `missing()` true. A compact block (format.h) is
// read the same way through its leaf record; a record that is damaged ends the walk
// like a missing block, since the entries after a bad one cannot be found.
class LeafTriangles {
public:
    LeafTriangles(LodLane& lane, const std::uint8_t* leaf_node, float priority)
        : lane_(lane), priority_(priority) {
        const std::uint32_t w = load<std::uint32_t>(leaf_node);
        left_ = format::leaf_count(w);
        entry_ = format::leaf_first(w);
        block_id_ = lane.level_first[lane.tri_level] + load<std::uint32_t>(leaf_node + 4);
        open(block_id_);
    }

    bool missing() const { return block_ == nullptr; }

    // The next triangle (its index in the current block); false at the end of the leaf
    // or when a block is missing.
    bool next(Vec3f& v0, Vec3f& v1, Vec3f& v2, std::uint32_t& local) {
        if (lane_.compact_triangles) return next_compact(v0, v1, v2, local);
        while (block_ && left_ > 0) {
            --left_;
            while (block_ && entry_ >= entries_) {  // a big leaf continues in the next block
                entry_ = 0;
                open(++block_id_);
            }
            if (!block_) return false;
            const std::uint32_t e = entry_++;
            local = load<std::uint16_t>(block_ + layout_.list + 2 * std::size_t{e});
            if (local >= tris_) continue;
            const std::uint8_t* corner = block_ + layout_.triangles + 6 * std::size_t{local};
            const std::uint32_t i0 = load<std::uint16_t>(corner), i1 = load<std::uint16_t>(corner + 2),
                                i2 = load<std::uint16_t>(corner + 4);
            if (i0 >= verts_ || i1 >= verts_ || i2 >= verts_) continue;
            v0 = layout_.vertex(block_, i0, lane_.vertex_steps);
            v1 = layout_.vertex(block_, i1, lane_.vertex_steps);
            v2 = layout_.vertex(block_, i2, lane_.vertex_steps);
            return true;
        }
        return false;
    }
    const std::uint8_t* block() const { return block_; }
    // The input id of triangle `local` of the current block, read only when needed: the
    // ids live in their own section, a cache line away from the vertices.
    std::uint32_t id(std::uint32_t local) const {
        if (lane_.compact_triangles) {
            return group_for(local) ? compact_.id(group_, local - group_.first) : kNoHit;
        }
        return load<std::uint32_t>(block_ + layout_.ids + 4 * std::size_t{local});
    }

private:
    void open(std::uint32_t id) {
        block_ = id < lane_.block_count ? lane_.lookup(id, priority_) : nullptr;
        if (!block_) return;
        if (lane_.compact_triangles) {
            // A damaged header or record: treat as missing. An empty leaf has no record.
            group_index_ = ~0u;
            record_left_ = 0;
            if (left_ == 0) return;
            if (!format::CompactTriangleBlock::parse(block_, format::kBlockSize, lane_.has_colours,
                                                     lane_.quantized_vertices, compact_) ||
                !record_.open(compact_, entry_, left_)) {
                block_ = nullptr;
                return;
            }
            record_left_ = record_.count();
            return;
        }
        entries_ = load<std::uint32_t>(block_);
        tris_ = load<std::uint32_t>(block_ + 4);
        verts_ = load<std::uint32_t>(block_ + 8);
        layout_ = format::TriangleBlockLayout::read(block_, lane_.has_colours, lane_.quantized_vertices);
        if (layout_.end > format::kBlockSize) block_ = nullptr;  // damaged header: treat as missing
    }

    bool next_compact(Vec3f& v0, Vec3f& v1, Vec3f& v2, std::uint32_t& local) {
        while (block_ && left_ > 0) {
            if (record_left_ == 0) {  // a big leaf continues at the next block's first record
                entry_ = format::compact::kHeader;
                open(++block_id_);
                if (!block_) return false;
            }
            --left_;
            --record_left_;
            if (!record_.next(local)) {
                block_ = nullptr;
                return false;
            }
            std::uint32_t v[3];
            if (!compact_.corners(local, v)) continue;
            if ((v[0] >= compact_.verts) | (v[1] >= compact_.verts) | (v[2] >= compact_.verts)) continue;
            v0 = compact_.vertex(v[0], lane_.vertex_steps);
            v1 = compact_.vertex(v[1], lane_.vertex_steps);
            v2 = compact_.vertex(v[2], lane_.vertex_steps);
            return true;
        }
        return false;
    }
    // Decodes the group holding triangle `local` unless it is the one decoded last (a
    // leaf's triangles mostly come in runs); false for a damaged group.
    bool group_for(std::uint32_t local) const {
        const std::uint32_t g = local / format::compact::kGroup;
        if (g == group_index_) return true;
        group_index_ = ~0u;
        if (!compact_.group(g, group_)) return false;
        group_index_ = g;
        return true;
    }

    LodLane& lane_;
    float priority_;
    const std::uint8_t* block_ = nullptr;
    std::uint32_t block_id_ = 0, left_ = 0, entry_ = 0, entries_ = 0, tris_ = 0, verts_ = 0;
    format::TriangleBlockLayout layout_;
    // Compact blocks: the block's view, the leaf record being read, the last group
    // (uninitialised until open() parses a compact block).
    format::CompactTriangleBlock compact_;
    format::CompactLeafRecord record_;
    std::uint32_t record_left_ = 0;
    mutable format::CompactTriangleBlock::Group group_;
    mutable std::uint32_t group_index_ = ~0u;
};

}  // namespace lod_detail

// The walk of one ray through the subtree at `node`, entered with the segment
// [tmin, tmax] by the face on `entry_axis`, below the voxel last passed (`voxel`).
// Closest hit (AnyHit = false) or any hit (AnyHit = true); voxels count as hits.
// Returns true when the ray is finished (its hit can no longer change: a voxel stood in,
// a hit lies inside its cell, an any-hit ray hit, or a node is damaged), false when the
// subtree is done and cells beyond it may still hold a nearer hit. lod_traverse() walks
// from the root; the packets hand their last live ray to it mid-tree.
template <bool AnyHit>
inline bool lod_walk(LodLane& lane, const LodRay& lray, const ShearedRay& sheared, lod_detail::NodeRef node,
                     float tmin, float tmax, int entry_axis, lod_detail::Voxel voxel, LodHit& hit,
                     std::uint32_t skip) {
    using namespace format;
    using lod_detail::load;
    using lod_detail::NodeRef;
    using lod_detail::Voxel;
    const Ray& ray = lray.ray;
    const float org[3] = {ray.org.x, ray.org.y, ray.org.z};
    const float inv[3] = {1.0f / ray.dir.x, 1.0f / ray.dir.y, 1.0f / ray.dir.z};
    const bool dir_negative[3] = {std::signbit(ray.dir.x), std::signbit(ray.dir.y), std::signbit(ray.dir.z)};
    struct Entry {
        NodeRef node;
        float tmin, tmax;
        int entry_axis;
        Voxel voxel;
    };
    Entry stack[64];
    int top = 0;
    auto take_voxel = [&](const Voxel& v, float t) {
        if (t < hit.t) lod_detail::hit_voxel(v, entry_axis, ray, t, hit);
        ++lane.voxel_hits;
        return true;
    };

    for (;;) {
        bool leaf = false;
        for (;;) {
            const std::uint32_t w = load<std::uint32_t>(node.block + node.off);
            if (!is_inner(w)) {
                leaf = true;
                break;
            }
            ++lane.node_visits;
            const int axis = axis_of(w);
            const float split = lod_detail::split_of(lane.quantized_splits, node, w);
            const std::uint8_t* child = nullptr;
            if (is_lod(w)) {
                const Voxel here = lod_detail::voxel_of(lane.quantized_splits, node, w);
                const float reach = lray.cone_t0 + tmin;
                if (here.radius <= reach * lray.cone) return take_voxel(here, tmin);
                child = lod_detail::lod_child_block(lane, node, here.radius / std::max(reach, 1e-30f));
                if (!child) return take_voxel(here, tmin);
                voxel = here;
            }
            NodeRef left, right;
            if (!lod_detail::children_of(lane.quantized_splits, node, w, split, child, left, right)) return true;  // damaged: stop here
            const float o = org[axis];
            const float t_split = (split - o) * inv[axis];
            const float abs_split = std::abs(t_split);
            const float slack = abs_split < std::numeric_limits<float>::infinity() ? abs_split * kSplitSlack : 0.0f;
            const float ts_lo = t_split - slack, ts_hi = t_split + slack;
            const bool below_first = o < split || (o == split && dir_negative[axis]);
            const NodeRef first = below_first ? left : right;
            const NodeRef second = below_first ? right : left;
            NodeRef next;
            if (t_split != t_split) {
                if (second.block && top < 64) stack[top++] = {second, tmin, tmax, entry_axis, voxel};
                next = first;
            } else if (ts_lo > tmax || t_split <= 0.0f) {
                next = first;
            } else if (ts_hi < tmin) {
                next = second;
            } else if (!first.block) {
                next = second;
                if (ts_lo > tmin) {
                    tmin = ts_lo;
                    entry_axis = axis;
                }
            } else {
                if (second.block && top < 64) {
                    stack[top++] = {second, std::max(tmin, ts_lo), tmax, ts_lo > tmin ? axis : entry_axis, voxel};
                }
                next = first;
                tmax = std::min(tmax, ts_hi);
            }
            if (!next.block) break;
            node = next;
        }
        if (leaf) {
            const float priority = voxel.samples ? voxel.radius / std::max(lray.cone_t0 + tmin, 1e-30f) : 0.0f;
            lod_detail::LeafTriangles triangles(lane, node.block + node.off, priority);
            Vec3f v0, v1, v2;
            std::uint32_t local;
            while (triangles.next(v0, v1, v2, local)) {
                if (skip != kNoHit && triangles.id(local) == skip) continue;
                ++lane.triangle_tests;
                if (intersect_triangle(ray, sheared, v0, v1, v2, hit)) {
                    hit.prim = triangles.id(local);
                    hit.tri_block = triangles.block();
                    hit.local = local;
                    if (AnyHit) return true;
                }
            }
            if (triangles.missing()) {
                // Triangles not here yet: the last voxel passed stands in for them.
                if (voxel.samples) return take_voxel(voxel, tmin);
            } else if (hit.prim != kNoHit && hit.t * (1.0f + kSplitSlack) < tmax) {
                return true;
            }
        }
        for (;;) {
            if (top == 0) return false;
            const Entry& e = stack[--top];
            if (e.tmin > hit.t) continue;
            node = e.node;
            tmin = e.tmin;
            tmax = e.tmax;
            entry_axis = e.entry_axis;
            voxel = e.voxel;
            break;
        }
    }
}

// Closest hit (AnyHit = false) or any hit (AnyHit = true) of one ray; voxels count as
// hits. `skip` is a triangle never reported (the surface a secondary ray leaves).
template <bool AnyHit>
inline bool lod_traverse(LodLane& lane, const Box3f& root_cell, const LodRay& lray, LodHit& hit,
                         std::uint32_t skip = kNoHit) {
    const Ray& ray = lray.ray;
    float tmin, tmax;
    int entry_axis;
    hit.t = ray.tmax;
    hit.prim = kNoHit;
    if (!lod_detail::clip_with_axis(ray, root_cell, tmin, tmax, entry_axis)) return false;
    const std::uint8_t* block = lane.lookup(lane.level_first[0], 0.0f);
    if (!block) return false;
    lod_walk<AnyHit>(lane, lray, ShearedRay(ray.dir), lod_detail::root_ref(block, root_cell), tmin, tmax, entry_axis,
                     {nullptr, 0.0f}, hit, skip);
    return hit.prim != kNoHit;
}

VASTRAY_KERNEL_END
