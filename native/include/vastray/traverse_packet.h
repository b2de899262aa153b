// Ray-packet traversal of the kd-tree (Wald 2004), for coherent rays such as the
// primary rays of a pixel block. Packets hold V SSE vectors of four rays (V = 1: a 2x2
// quad, V = 4: a 4x4 block). One node fetch and one decision serve all 4V rays;
// per-ray segments [tmin, tmax] stay in SSE registers, and a ray whose segment is empty
// simply stops influencing the decisions. Triangle tests stay scalar and watertight
// (the same test as single rays), so packets change speed, never answers.
//
// Preconditions (checked by packet_is_coherent): every direction component is non-zero
// and has the same sign across the packet, so all rays order the children alike.
#pragma once

#if defined(__SSE2__)
#include <emmintrin.h>
#include <xmmintrin.h>
#define VASTRAY_HAVE_PACKETS 1
#endif

#include <new>

#include "vastray/traverse.h"

namespace vastray {

inline bool packet_is_coherent(const Ray* rays, int count) {
    for (int a = 0; a < 3; ++a) {
        const float d0 = rays[0].dir[a];
        if (d0 == 0.0f) return false;
        for (int k = 1; k < count; ++k) {
            const float d = rays[k].dir[a];
            if (d == 0.0f || std::signbit(d) != std::signbit(d0)) return false;
        }
    }
    return true;
}

#if defined(VASTRAY_HAVE_PACKETS)

// Closest hits of 4V coherent rays; hits[k] gets ray k's result.
template <int V>
inline void traverse_packet(const KdTree& tree, const Vec3f* tri_vertices, const Ray* rays, Hit* hits,
                            TraversalCounters& counters) {
    constexpr int N = 4 * V;
    alignas(16) float lo[N], hi[N];
    bool any_active = false;
    for (int k = 0; k < N; ++k) {
        hits[k] = Hit{};
        hits[k].t = rays[k].tmax;
        float t0, t1;
        if (clip_ray_to_box(rays[k], tree.bounds, t0, t1)) {
            lo[k] = t0;
            hi[k] = t1;
            any_active = true;
        } else {
            lo[k] = std::numeric_limits<float>::infinity();
            hi[k] = -std::numeric_limits<float>::infinity();
        }
    }
    if (!any_active) return;
    // Shear constants once per ray, not once per leaf visit.
    alignas(16) unsigned char sheared_storage[N * sizeof(ShearedRay)];
    ShearedRay* sheared = reinterpret_cast<ShearedRay*>(sheared_storage);
    for (int k = 0; k < N; ++k) new (sheared + k) ShearedRay(rays[k].dir);
    __m128 org[3][V], inv[3][V];
    for (int a = 0; a < 3; ++a) {
        for (int v = 0; v < V; ++v) {
            const Ray* r = rays + 4 * v;
            org[a][v] = _mm_setr_ps(r[0].org[a], r[1].org[a], r[2].org[a], r[3].org[a]);
            inv[a][v] = _mm_div_ps(_mm_set1_ps(1.0f), _mm_setr_ps(r[0].dir[a], r[1].dir[a], r[2].dir[a], r[3].dir[a]));
        }
    }
    // With equal signs, "below first" is the same for every ray of the packet.
    const bool below_first[3] = {!std::signbit(rays[0].dir.x), !std::signbit(rays[0].dir.y),
                                 !std::signbit(rays[0].dir.z)};
    const __m128 slack_scale = _mm_set1_ps(kSplitSlack);
    const __m128 sign_mask = _mm_set1_ps(-0.0f);

    struct alignas(16) Entry {
        __m128 tmin[V], tmax[V];
        std::uint32_t node;
    };
    Entry stack[64];
    int top = 0;
    std::uint64_t node_visits = 0, triangle_tests = 0;
    __m128 tmin[V], tmax[V], hit_t[V];
    for (int v = 0; v < V; ++v) {
        tmin[v] = _mm_load_ps(lo + 4 * v);
        tmax[v] = _mm_load_ps(hi + 4 * v);
        hit_t[v] = _mm_setr_ps(hits[4 * v].t, hits[4 * v + 1].t, hits[4 * v + 2].t, hits[4 * v + 3].t);
    }
    const KdNode* nodes = tree.nodes.data();
    std::uint32_t index = 0;
    for (;;) {
        const KdNode* node = nodes + index;
        bool descend = true;
        while (!node->is_leaf()) {
            ++node_visits;
            const int axis = node->axis();
            const __m128 split = _mm_set1_ps(node->split());
            const std::uint32_t left = node->left_empty() ? 0u : index + 1;
            const std::uint32_t right = node->right_empty() ? 0u : index + node->right_offset();
            const std::uint32_t near_child = below_first[axis] ? left : right;
            const std::uint32_t far_child = below_first[axis] ? right : left;
            // Each ray's part of its segment on either side of the plane, overlapping by
            // the same slack as single rays; an empty part (tmin > tmax) makes the ray
            // inactive in that child.
            __m128 near_tmax[V], far_tmin[V];
            int near_mask = 0, far_mask = 0;
            for (int v = 0; v < V; ++v) {
                const __m128 t_split = _mm_mul_ps(_mm_sub_ps(split, org[axis][v]), inv[axis][v]);
                const __m128 slack = _mm_mul_ps(_mm_andnot_ps(sign_mask, t_split), slack_scale);
                near_tmax[v] = _mm_min_ps(_mm_add_ps(t_split, slack), tmax[v]);
                far_tmin[v] = _mm_max_ps(_mm_sub_ps(t_split, slack), tmin[v]);
                near_mask |= _mm_movemask_ps(_mm_cmple_ps(tmin[v], near_tmax[v]));
                far_mask |= _mm_movemask_ps(_mm_cmple_ps(far_tmin[v], tmax[v]));
            }
            const bool near_active = near_child != 0 && near_mask != 0;
            const bool far_active = far_child != 0 && far_mask != 0;
            if (near_active) {
                if (far_active && top < 64) {
                    for (int v = 0; v < V; ++v) {
                        stack[top].tmin[v] = far_tmin[v];
                        stack[top].tmax[v] = tmax[v];
                    }
                    stack[top].node = far_child;
                    ++top;
                }
                for (int v = 0; v < V; ++v) tmax[v] = near_tmax[v];
                index = near_child;
            } else if (far_active) {
                for (int v = 0; v < V; ++v) tmin[v] = far_tmin[v];
                index = far_child;
            } else {
                descend = false;
                break;
            }
            node = nodes + index;
        }
        if (descend) {
            for (int v = 0; v < V; ++v) {
                _mm_store_ps(lo + 4 * v, tmin[v]);
                _mm_store_ps(hi + 4 * v, tmax[v]);
            }
            const std::uint32_t count = node->count();
            const std::uint32_t* ids = tree.tri_ids.data() + node->first();
            for (int k = 0; k < N; ++k) {
                if (!(lo[k] <= hi[k])) continue;
                for (std::uint32_t i = 0; i < count; ++i) {
                    const std::uint32_t id = ids[i];
                    ++triangle_tests;
                    const Vec3f* p = tri_vertices + 3 * static_cast<std::size_t>(id);
                    if (intersect_triangle(rays[k], sheared[k], p[0], p[1], p[2], hits[k])) hits[k].prim = id;
                }
            }
            for (int v = 0; v < V; ++v) {
                hit_t[v] = _mm_setr_ps(hits[4 * v].t, hits[4 * v + 1].t, hits[4 * v + 2].t, hits[4 * v + 3].t);
            }
        }
        // Pop the next subtree in which some ray still has a segment before its hit.
        // Clipping each segment to the ray's hit retires rays that are finished, the
        // packet form of the single-ray early exit.
        for (;;) {
            if (top == 0) {
                counters.node_visits += node_visits;
                counters.triangle_tests += triangle_tests;
                return;
            }
            --top;
            int active = 0;
            for (int v = 0; v < V; ++v) {
                tmin[v] = stack[top].tmin[v];
                tmax[v] = _mm_min_ps(stack[top].tmax[v], hit_t[v]);
                active |= _mm_movemask_ps(_mm_cmple_ps(tmin[v], tmax[v]));
            }
            if (active != 0) {
                index = stack[top].node;
                break;
            }
        }
    }
}

#endif  // VASTRAY_HAVE_PACKETS

}  // namespace vastray
