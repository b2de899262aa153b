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

    using lod_detail::NodeRef;
    struct Entry {
        NodeRef node;
        Voxel voxel;
        float tmin[N], tmax[N];
        std::int8_t axis[N];
    };
    Entry stack[64];
    int top = 0;
    NodeRef node{root, 0, 0};
    Voxel voxel{nullptr, 0.0f};

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
            const std::uint8_t* child = nullptr;
            if (is_lod(w)) {
                const Voxel here = lod_detail::voxel_of(node, w);
                float nearest = kInf;
                for (int i = 0; i < N; ++i) {
                    if (!(active >> i & 1u)) continue;
                    if (here.radius <= (cone_t0 + tmin[i]) * cone) take_voxel(here, i);
                    else nearest = std::min(nearest, tmin[i]);
                }
                if (!(active & live)) break;
                child = lod_detail::lod_child_block(lane, node, here.radius / std::max(cone_t0 + nearest, 1e-30f));
                if (!child) {
                    for (int i = 0; i < N; ++i) {
                        if (active >> i & live >> i & 1u) take_voxel(here, i);
                    }
                    break;
                }
                voxel = here;
            }
            NodeRef left, right;
            if (!lod_detail::children_of(node, w, child, left, right)) return;  // damaged node
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
            float nearest = kInf;
            for (int i = 0; i < N; ++i) {
                if (active >> i & 1u) nearest = std::min(nearest, tmin[i]);
            }
            const float priority = voxel.samples ? voxel.radius / std::max(cone_t0 + nearest, 1e-30f) : 0.0f;
            lod_detail::LeafTriangles triangles(lane, node.block + node.off, priority);
            Vec3f v0, v1, v2;
            std::uint32_t id, local;
            while (triangles.next(v0, v1, v2, id, local)) {
                for (int i = 0; i < N; ++i) {
                    if (!(active >> i & 1u)) continue;
                    ++lane.triangle_tests;
                    if (intersect_triangle(rays[i].ray, sheared[i], v0, v1, v2, hits[i])) {
                        hits[i].prim = id;
                        hits[i].tri_block = triangles.block();
                        hits[i].local = local;
                    }
                }
            }
            const bool missing = triangles.missing();
            for (int i = 0; i < N; ++i) {
                if (!(active >> i & 1u)) continue;
                if (missing) {
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
