// Packet version of lod_traverse for primary rays: N rays from one origin (a 4x4 pixel
// block) walk the cached tree together. One node fetch, one block lookup and one
// near/far decision serve the whole packet; each ray keeps its own segment, LOD test,
// voxel hit and termination, computed with exactly the single-ray arithmetic, so a
// packet changes speed, never answers (tests compare full-detail frames bit for bit).
//
// Preconditions (lod_packet_is_coherent): a shared origin, and every direction
// component non-zero with the same sign across the packet, so that every ray orders
// the children of every node alike.
#pragma once

#include "vastray/lod_traverse.h"

namespace vastray {

template <int N>
inline bool lod_packet_is_coherent(const LodRay* rays) {
    for (int a = 0; a < 3; ++a) {
        const float d0 = rays[0].ray.dir[a];
        if (d0 == 0.0f) return false;
        for (int k = 1; k < N; ++k) {
            const float d = rays[k].ray.dir[a];
            if (d == 0.0f || std::signbit(d) != std::signbit(d0) || rays[k].ray.org.x != rays[0].ray.org.x ||
                rays[k].ray.org.y != rays[0].ray.org.y || rays[k].ray.org.z != rays[0].ray.org.z) return false;
        }
    }
    return true;
}

template <int N>
inline void lod_traverse_packet(LodLane& lane, const Box3f& root_cell, const LodRay* rays, LodHit* hits) {
    static_assert(N <= 32, "ray masks are 32-bit");
    using namespace format;
    using lod_detail::load;
    using lod_detail::Voxel;
    constexpr float kInf = std::numeric_limits<float>::infinity();

    float tmin[N], tmax[N], inv[3][N];
    std::int8_t axis_in[N];  // entry axis per ray
    ShearedRay sheared[N];
    const float org[3] = {rays[0].ray.org.x, rays[0].ray.org.y, rays[0].ray.org.z};
    const float cone = rays[0].cone, cone_t0 = rays[0].cone_t0;
    std::uint32_t live = 0;  // rays that may still change their hit
    for (int i = 0; i < N; ++i) {
        const Ray& r = rays[i].ray;
        hits[i].t = r.tmax;
        hits[i].prim = kNoHit;
        for (int a = 0; a < 3; ++a) inv[a][i] = 1.0f / r.dir[a];
        int axis = 0;
        if (lod_detail::clip_with_axis(r, root_cell, tmin[i], tmax[i], axis)) {
            live |= 1u << i;
        } else {
            tmin[i] = kInf;
            tmax[i] = -kInf;
        }
        axis_in[i] = static_cast<std::int8_t>(axis);
        sheared[i] = ShearedRay(r.dir);
    }
    if (!live) return;
    const std::uint8_t* root = lane.lookup(lane.level_first[0], 0.0f);
    if (!root) return;

    // All rays share the origin, so they all order children alike.
    bool dir_negative[3];
    for (int a = 0; a < 3; ++a) dir_negative[a] = std::signbit(rays[0].ray.dir[a]);

    struct NodeRef {
        const std::uint8_t* block;
        std::uint32_t off, level;
    };
    struct Entry {
        NodeRef node;
        Voxel voxel;
        float tmin[N], tmax[N];
        std::int8_t axis[N];
    };
    Entry stack[64];
    int top = 0;
    NodeRef node{root, 0, 0};
    Voxel voxel;
    const std::uint32_t last_node_level = lane.tri_level - 1;

    // Ray i stops at voxel v, entered at its current tmin.
    auto take_voxel = [&](const Voxel& v, int i) {
        if (tmin[i] < hits[i].t) lod_detail::hit_voxel(v, axis_in[i], rays[i].ray, tmin[i], hits[i]);
        ++lane.voxel_hits;
        live &= ~(1u << i);
    };
    auto active_mask = [&]() {
        std::uint32_t m = 0;
        for (int i = 0; i < N; ++i) m |= (tmin[i] <= tmax[i] ? 1u : 0u) << i;
        return m & live;
    };

    for (;;) {
        bool leaf = false;
        for (;;) {
            const std::uint32_t active = active_mask();
            if (!active) break;
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
                float nearest = kInf;
                for (int i = 0; i < N; ++i) {
                    if (!(active >> i & 1u)) continue;
                    if (here.radius <= (cone_t0 + tmin[i]) * cone) take_voxel(here, i);
                    else nearest = std::min(nearest, tmin[i]);
                }
                if (!(active & live)) break;
                const std::uint8_t* child = nullptr;
                if (node.level < last_node_level) {
                    const std::uint32_t child_block =
                        lane.level_first[node.level + 1] + load<std::uint32_t>(node.block + node.off + 12);
                    if (child_block < lane.level_first[node.level + 2]) {
                        child = lane.lookup(child_block, here.radius / std::max(cone_t0 + nearest, 1e-30f));
                    }
                }
                if (!child) {
                    for (int i = 0; i < N; ++i) {
                        if (active >> i & live >> i & 1u) take_voxel(here, i);
                    }
                    break;
                }
                const std::uint32_t first = 8 * lod_child_off8(w);
                if (has_l) left = {child, first, node.level + 1};
                if (has_r) right = {child, has_l ? first + 8 * lod_right_from_left8(w) : first, node.level + 1};
                voxel = here;
            } else {
                if (has_l) left = {node.block, node.off + 8, node.level};
                const std::uint32_t r8 = basic_right_off8(w);
                if (has_r) right = {node.block, has_l ? node.off + 8 * r8 : node.off + 8, node.level};
                if (has_l && has_r && r8 < 2) return;  // damaged node: stop, never loop
            }
            if ((left.block && left.off > kBlockSize - 8) || (right.block && right.off > kBlockSize - 8)) return;
            const float o = org[axis];
            const bool below_first = o < split || (o == split && dir_negative[axis]);
            const NodeRef first = below_first ? left : right;
            const NodeRef second = below_first ? right : left;
            // Per ray, the single-ray cases as segments: [near_lo, near_hi] in the first
            // child, [far_lo, far_hi] in the second (empty when lo > hi).
            float near_hi[N], far_lo[N], far_hi[N];
            std::uint32_t any_near = 0, any_far = 0;
            for (int i = 0; i < N; ++i) {
                const float t_split = (split - o) * inv[axis][i];
                const float abs_split = std::abs(t_split);
                const float slack = abs_split < kInf ? abs_split * kSplitSlack : 0.0f;
                const float ts_lo = t_split - slack, ts_hi = t_split + slack;
                if (t_split != t_split) {
                    near_hi[i] = tmax[i];
                    far_lo[i] = tmin[i];
                } else if (t_split <= 0.0f) {
                    near_hi[i] = tmax[i];
                    far_lo[i] = kInf;
                } else {
                    near_hi[i] = std::min(tmax[i], ts_hi);
                    far_lo[i] = std::max(tmin[i], ts_lo);
                }
                far_hi[i] = tmax[i];
                const std::uint32_t bit = active >> i & 1u;
                any_near |= (tmin[i] <= near_hi[i] ? bit : 0u) << i;
                any_far |= (far_lo[i] <= far_hi[i] ? bit : 0u) << i;
            }
            if (!first.block) any_near = 0;
            if (!second.block) any_far = 0;
            if (any_near && any_far && top < 64) {
                Entry& e = stack[top++];
                e.node = second;
                e.voxel = voxel;
                for (int i = 0; i < N; ++i) {
                    const bool in = any_far >> i & 1u;
                    e.tmin[i] = in ? far_lo[i] : kInf;
                    e.tmax[i] = in ? far_hi[i] : -kInf;
                    e.axis[i] = far_lo[i] > tmin[i] ? static_cast<std::int8_t>(axis) : axis_in[i];
                }
            }
            if (any_near) {
                for (int i = 0; i < N; ++i) {
                    if (any_near >> i & 1u) {
                        tmax[i] = near_hi[i];
                    } else {
                        tmin[i] = kInf;
                        tmax[i] = -kInf;
                    }
                }
                node = first;
            } else if (any_far) {
                for (int i = 0; i < N; ++i) {
                    if (any_far >> i & 1u) {
                        if (far_lo[i] > tmin[i]) axis_in[i] = static_cast<std::int8_t>(axis);
                        tmin[i] = far_lo[i];
                    } else {
                        tmin[i] = kInf;
                        tmax[i] = -kInf;
                    }
                }
                node = second;
            } else {
                break;
            }
        }
        if (leaf) {
            const std::uint32_t active = active_mask();
            const std::uint32_t w = load<std::uint32_t>(node.block + node.off);
            const std::uint32_t count = leaf_count(w);
            std::uint32_t tri_block = lane.level_first[lane.tri_level] + load<std::uint32_t>(node.block + node.off + 4);
            float nearest = kInf;
            for (int i = 0; i < N; ++i) {
                if (active >> i & 1u) nearest = std::min(nearest, tmin[i]);
            }
            const float priority = voxel.samples ? voxel.radius / std::max(cone_t0 + nearest, 1e-30f) : 0.0f;
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
            for (std::uint32_t k = 0; tb && k < count; ++k, ++entry) {
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
                const std::uint8_t* corner = tb + l.triangles + 6 * std::size_t{local};
                const std::uint32_t i0 = load<std::uint16_t>(corner), i1 = load<std::uint16_t>(corner + 2),
                                    i2 = load<std::uint16_t>(corner + 4);
                if (i0 >= verts || i1 >= verts || i2 >= verts) continue;
                const Vec3f v0 = load<Vec3f>(tb + l.vertices + 12 * std::size_t{i0});
                const Vec3f v1 = load<Vec3f>(tb + l.vertices + 12 * std::size_t{i1});
                const Vec3f v2 = load<Vec3f>(tb + l.vertices + 12 * std::size_t{i2});
                const std::uint32_t id = load<std::uint32_t>(tb + l.ids + 4 * std::size_t{local});
                for (int i = 0; i < N; ++i) {
                    if (!(active >> i & 1u)) continue;
                    ++lane.triangle_tests;
                    if (intersect_triangle(rays[i].ray, sheared[i], v0, v1, v2, hits[i])) {
                        hits[i].prim = id;
                        hits[i].tri_block = tb;
                        hits[i].local = local;
                    }
                }
            }
            for (int i = 0; i < N; ++i) {
                if (!(active >> i & 1u)) continue;
                if (!tb) {
                    if (voxel.samples) take_voxel(voxel, i);
                } else if (hits[i].prim != kNoHit && hits[i].t * (1.0f + kSplitSlack) < tmax[i]) {
                    live &= ~(1u << i);
                }
            }
        }
        for (;;) {
            if (top == 0 || !live) return;
            const Entry& e = stack[--top];
            std::uint32_t any = 0;
            for (int i = 0; i < N; ++i) {
                const bool in = (live >> i & 1u) && e.tmin[i] <= e.tmax[i] && !(e.tmin[i] > hits[i].t);
                tmin[i] = in ? e.tmin[i] : kInf;
                tmax[i] = in ? e.tmax[i] : -kInf;
                axis_in[i] = e.axis[i];
                any |= in ? 1u : 0u;
            }
            if (!any) continue;
            node = e.node;
            voxel = e.voxel;
            break;
        }
    }
}

}  // namespace vastray
