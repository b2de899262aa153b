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
#include "vastray/traverse.h"

namespace vastray {

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
struct Voxel {
    const std::uint8_t* samples = nullptr;
    float radius = 0;
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

}  // namespace lod_detail

// Closest hit (AnyHit = false) or any hit (AnyHit = true); voxels count as hits.
template <bool AnyHit>
inline bool lod_traverse(LodLane& lane, const Box3f& root_cell, const LodRay& lray, LodHit& hit,
                         std::uint32_t skip = kNoHit) {
    using namespace format;
    using lod_detail::load;
    using lod_detail::Voxel;
    const Ray& ray = lray.ray;
    float tmin, tmax;
    int entry_axis;
    hit.t = ray.tmax;
    hit.prim = kNoHit;
    if (!lod_detail::clip_with_axis(ray, root_cell, tmin, tmax, entry_axis)) return false;
    const std::uint8_t* block = lane.lookup(lane.level_first[0], 0.0f);
    if (!block) return false;

    const ShearedRay sheared(ray.dir);
    const float org[3] = {ray.org.x, ray.org.y, ray.org.z};
    const float inv[3] = {1.0f / ray.dir.x, 1.0f / ray.dir.y, 1.0f / ray.dir.z};
    const bool dir_negative[3] = {std::signbit(ray.dir.x), std::signbit(ray.dir.y), std::signbit(ray.dir.z)};
    struct NodeRef {
        const std::uint8_t* block;
        std::uint32_t off, level;
    };
    struct Entry {
        NodeRef node;
        float tmin, tmax;
        int entry_axis;
        Voxel voxel;
    };
    Entry stack[64];
    int top = 0;
    NodeRef node{block, 0, 0};
    Voxel voxel;  // the last voxel passed on the way to `node`
    const std::uint32_t last_node_level = lane.tri_level - 1;

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
            const float split = bits_float(load<std::uint32_t>(node.block + node.off + 4));
            const bool has_l = (w & kLeftEmpty) == 0, has_r = (w & kRightEmpty) == 0;
            NodeRef left{nullptr, 0, 0}, right{nullptr, 0, 0};
            if (is_lod(w)) {
                const Voxel here{node.block + node.off + 4 * lod_voxel_off4(w),
                                 bits_float(load<std::uint32_t>(node.block + node.off + 8))};
                const float reach = lray.cone_t0 + tmin;
                if (here.radius <= reach * lray.cone) return take_voxel(here, tmin);
                if (node.level >= last_node_level) return take_voxel(here, tmin);  // damaged: no level below
                const std::uint32_t child_block = lane.level_first[node.level + 1] + load<std::uint32_t>(node.block + node.off + 12);
                const std::uint8_t* child =
                    child_block < lane.level_first[node.level + 2] ? lane.lookup(child_block, here.radius / std::max(reach, 1e-30f))
                                                                   : nullptr;
                if (!child) return take_voxel(here, tmin);
                const std::uint32_t first = 8 * lod_child_off8(w);
                if (has_l) left = {child, first, node.level + 1};
                if (has_r) right = {child, has_l ? first + 8 * lod_right_from_left8(w) : first, node.level + 1};
                voxel = here;
            } else {
                if (has_l) left = {node.block, node.off + 8, node.level};
                const std::uint32_t r8 = basic_right_off8(w);
                if (has_r) right = {node.block, has_l ? node.off + 8 * r8 : node.off + 8, node.level};
                if (has_l && has_r && r8 < 2) return hit.prim != kNoHit;  // damaged node: stop, never loop
            }
            if ((left.block && left.off > kBlockSize - 8) || (right.block && right.off > kBlockSize - 8)) {
                return hit.prim != kNoHit;  // damaged block: offsets past its end
            }
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
            const std::uint32_t w = load<std::uint32_t>(node.block + node.off);
            const std::uint32_t count = leaf_count(w);
            std::uint32_t tri_block = lane.level_first[lane.tri_level] + load<std::uint32_t>(node.block + node.off + 4);
            const float priority = voxel.samples ? voxel.radius / std::max(lray.cone_t0 + tmin, 1e-30f) : 0.0f;
            const std::uint8_t* tb = tri_block < lane.block_count ? lane.lookup(tri_block, priority) : nullptr;
            std::uint32_t entry = leaf_first(w);
            std::uint32_t entries = 0, tris = 0, verts = 0;
            TriangleBlockLayout l;
            auto open_block = [&] {
                entries = load<std::uint32_t>(tb);
                tris = load<std::uint32_t>(tb + 4);
                verts = load<std::uint32_t>(tb + 8);
                l = TriangleBlockLayout::of(entries, tris, verts, lane.has_colours);
                if (l.end > kBlockSize) tb = nullptr;  // damaged header: treat as missing
            };
            if (tb) open_block();
            for (std::uint32_t i = 0; tb && i < count; ++i, ++entry) {
                while (tb && entry >= entries) {
                    // A leaf too big for one block continues at entry 0 of the next.
                    ++tri_block;
                    tb = tri_block < lane.block_count ? lane.lookup(tri_block, priority) : nullptr;
                    entry = 0;
                    if (tb) open_block();
                }
                if (!tb) break;
                const std::uint32_t local = load<std::uint16_t>(tb + l.list + 2 * std::size_t{entry});
                if (local >= tris) continue;
                const std::uint32_t id = load<std::uint32_t>(tb + l.ids + 4 * std::size_t{local});
                if (id == skip) continue;
                const std::uint8_t* corner = tb + l.triangles + 6 * std::size_t{local};
                const std::uint32_t i0 = load<std::uint16_t>(corner), i1 = load<std::uint16_t>(corner + 2),
                                    i2 = load<std::uint16_t>(corner + 4);
                if (i0 >= verts || i1 >= verts || i2 >= verts) continue;
                ++lane.triangle_tests;
                const Vec3f v0 = load<Vec3f>(tb + l.vertices + 12 * std::size_t{i0});
                const Vec3f v1 = load<Vec3f>(tb + l.vertices + 12 * std::size_t{i1});
                const Vec3f v2 = load<Vec3f>(tb + l.vertices + 12 * std::size_t{i2});
                if (intersect_triangle(ray, sheared, v0, v1, v2, hit)) {
                    hit.prim = id;
                    hit.tri_block = tb;
                    hit.local = local;
                    if (AnyHit) return true;
                }
            }
            if (!tb) {
                // Triangles not here yet: the last voxel passed stands in for them.
                if (voxel.samples) return take_voxel(voxel, tmin);
            } else if (hit.prim != kNoHit && hit.t * (1.0f + kSplitSlack) < tmax) {
                return true;
            }
        }
        for (;;) {
            if (top == 0) return hit.prim != kNoHit;
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

}  // namespace vastray
