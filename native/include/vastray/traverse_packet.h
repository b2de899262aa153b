// Four-ray packet traversal of the kd-tree (Wald 2004), for coherent rays such as the
// primary rays of a 2x2 pixel quad. One node fetch and one decision serve four rays;
// per-ray segments [tmin, tmax] are kept in SSE registers, and a ray whose segment is
// empty simply stops influencing the decisions. Triangle tests stay scalar and
// watertight (the same test as single rays), so packets change speed, never answers.
//
// Preconditions (checked by packet_is_coherent): every direction component is non-zero
// and has the same sign across the packet, so all four rays order the children alike.
#pragma once

#if defined(__SSE2__)
#include <emmintrin.h>
#include <xmmintrin.h>
#define VASTRAY_HAVE_PACKETS 1
#endif

#include "vastray/traverse.h"

namespace vastray {

inline bool packet_is_coherent(const Ray* rays) {
    for (int a = 0; a < 3; ++a) {
        const float d0 = rays[0].dir[a];
        if (d0 == 0.0f) return false;
        for (int k = 1; k < 4; ++k) {
            const float d = rays[k].dir[a];
            if (d == 0.0f || std::signbit(d) != std::signbit(d0)) return false;
        }
    }
    return true;
}

#if defined(VASTRAY_HAVE_PACKETS)

// Closest hits of four coherent rays; hits[k] gets ray k's result.
inline void traverse_packet4(const KdTree& tree, const Vec3f* tri_vertices, const Ray* rays, Hit* hits,
                             TraversalCounters& counters) {
    alignas(16) float tmin_init[4], tmax_init[4];
    const ShearedRay sheared[4] = {ShearedRay(rays[0].dir), ShearedRay(rays[1].dir), ShearedRay(rays[2].dir),
                             ShearedRay(rays[3].dir)};
    for (int k = 0; k < 4; ++k) {
        hits[k] = Hit{};
        hits[k].t = rays[k].tmax;
        float t0, t1;
        if (clip_ray_to_box(rays[k], tree.bounds, t0, t1)) {
            tmin_init[k] = t0;
            tmax_init[k] = t1;
        } else {
            tmin_init[k] = std::numeric_limits<float>::infinity();
            tmax_init[k] = -std::numeric_limits<float>::infinity();
        }
    }
    __m128 org[3], inv[3];
    for (int a = 0; a < 3; ++a) {
        org[a] = _mm_setr_ps(rays[0].org[a], rays[1].org[a], rays[2].org[a], rays[3].org[a]);
        inv[a] = _mm_div_ps(_mm_set1_ps(1.0f),
                            _mm_setr_ps(rays[0].dir[a], rays[1].dir[a], rays[2].dir[a], rays[3].dir[a]));
    }
    // With equal signs, "below first" is the same for all four rays.
    const bool below_first[3] = {!std::signbit(rays[0].dir.x), !std::signbit(rays[0].dir.y),
                                 !std::signbit(rays[0].dir.z)};

    struct alignas(16) Entry {
        __m128 tmin, tmax;
        std::uint32_t node;
    };
    Entry stack[64];
    int top = 0;
    std::uint64_t node_visits = 0, triangle_tests = 0;
    __m128 tmin = _mm_load_ps(tmin_init), tmax = _mm_load_ps(tmax_init);
    if (_mm_movemask_ps(_mm_cmple_ps(tmin, tmax)) == 0) return;
    __m128 hit_t = _mm_setr_ps(hits[0].t, hits[1].t, hits[2].t, hits[3].t);
    const KdNode* nodes = tree.nodes.data();
    std::uint32_t index = 0;
    for (;;) {
        const KdNode* node = nodes + index;
        bool descend = true;
        while (!node->is_leaf()) {
            ++node_visits;
            const int axis = node->axis();
            const __m128 t_split = _mm_mul_ps(_mm_sub_ps(_mm_set1_ps(node->split()), org[axis]), inv[axis]);
            const std::uint32_t left = node->left_empty() ? 0u : index + 1;
            const std::uint32_t right = node->right_empty() ? 0u : index + node->right_offset();
            const std::uint32_t near_child = below_first[axis] ? left : right;
            const std::uint32_t far_child = below_first[axis] ? right : left;
            // Each ray's part of the segment on either side of the plane; empty parts
            // (tmin > tmax) make a ray inactive in that child.
            // The same slack as single rays: segments on both sides overlap by a few ulps.
            const __m128 abs_split = _mm_andnot_ps(_mm_set1_ps(-0.0f), t_split);
            const __m128 slack = _mm_mul_ps(abs_split, _mm_set1_ps(kSplitSlack));
            const __m128 near_tmax = _mm_min_ps(_mm_add_ps(t_split, slack), tmax);
            const __m128 far_tmin = _mm_max_ps(_mm_sub_ps(t_split, slack), tmin);
            const bool near_active = near_child != 0 && _mm_movemask_ps(_mm_cmple_ps(tmin, near_tmax)) != 0;
            const bool far_active = far_child != 0 && _mm_movemask_ps(_mm_cmple_ps(far_tmin, tmax)) != 0;
            if (near_active) {
                if (far_active && top < 64) {
                    stack[top].tmin = far_tmin;
                    stack[top].tmax = tmax;
                    stack[top].node = far_child;
                    ++top;
                }
                tmax = near_tmax;
                index = near_child;
            } else if (far_active) {
                tmin = far_tmin;
                index = far_child;
            } else {
                descend = false;
                break;
            }
            node = nodes + index;
        }
        if (descend) {
            alignas(16) float lo[4], hi[4], ht[4];
            _mm_store_ps(lo, tmin);
            _mm_store_ps(hi, tmax);
            const std::uint32_t count = node->count();
            const std::uint32_t* ids = tree.tri_ids.data() + node->first();
            for (int k = 0; k < 4; ++k) {
                if (!(lo[k] <= hi[k])) continue;
                for (std::uint32_t i = 0; i < count; ++i) {
                    const std::uint32_t id = ids[i];
                    ++triangle_tests;
                    const Vec3f* v = tri_vertices + 3 * static_cast<std::size_t>(id);
                    if (intersect_triangle(rays[k], sheared[k], v[0], v[1], v[2], hits[k])) hits[k].prim = id;
                }
            }
            for (int k = 0; k < 4; ++k) ht[k] = hits[k].t;
            hit_t = _mm_load_ps(ht);
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
            tmin = stack[top].tmin;
            tmax = _mm_min_ps(stack[top].tmax, hit_t);
            if (_mm_movemask_ps(_mm_cmple_ps(tmin, tmax)) != 0) {
                index = stack[top].node;
                break;
            }
        }
    }
}

#endif  // VASTRAY_HAVE_PACKETS

}  // namespace vastray
