// Ray-packet traversal of the kd-tree (Wald 2004), for coherent rays such as the
// primary rays of a pixel block. Packets hold V SSE vectors of four rays (V = 1: a 2x2
// quad, V = 4: a 4x4 block). One node fetch and one decision serve all 4V rays;
// per-ray segments [tmin, tmax] stay in SSE registers, and a ray whose segment is empty
// simply stops influencing the decisions. Leaves test one triangle against four rays
// with the float operations of the scalar watertight test, so packets change speed,
// never answers.
//
// Preconditions (checked by packet_is_coherent): every direction component is non-zero
// and has the same sign across the packet, so all rays order the children alike.
#pragma once

#if defined(__SSE2__)
#include <emmintrin.h>
#include <cstdint>
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

// The closest hits of four rays, structure-of-arrays, for the SIMD leaf test.
struct Hit4 {
    __m128 t, u, v;
    __m128i prim;

    static Hit4 load(const Hit* h) {
        return {_mm_setr_ps(h[0].t, h[1].t, h[2].t, h[3].t), _mm_setr_ps(h[0].u, h[1].u, h[2].u, h[3].u),
                _mm_setr_ps(h[0].v, h[1].v, h[2].v, h[3].v),
                _mm_setr_epi32(static_cast<int>(h[0].prim), static_cast<int>(h[1].prim), static_cast<int>(h[2].prim),
                               static_cast<int>(h[3].prim))};
    }
    void store(Hit* h) const {
        alignas(16) float st[4], su[4], sv[4];
        alignas(16) std::uint32_t sp[4];
        _mm_store_ps(st, t);
        _mm_store_ps(su, u);
        _mm_store_ps(sv, v);
        _mm_store_si128(reinterpret_cast<__m128i*>(sp), prim);
        for (int k = 0; k < 4; ++k) h[k] = Hit{st[k], sp[k], su[k], sv[k]};
    }
};

// Four rays sharing one shear permutation (kx, ky, kz), in SSE registers, for testing
// one triangle against four rays at once in a packet's leaf.
struct ShearedRay4 {
    int kx, ky, kz;
    __m128 ox, oy, oz;  // origins, permuted into the shear frame
    __m128 sx, sy, sz;
    __m128 tmin;        // each ray's own tmin
};

// The watertight test of triangle.h on four rays at once, with the same float
// operations in the same order, so each lane gets bit-for-bit the single-ray answer.
// Lanes whose edge functions hit exactly zero are finished by the scalar test, which
// re-evaluates them in double. `active` marks the lanes to test; hits are SoA.
inline void intersect_triangle4(const ShearedRay4& r, const Ray* rays, const ShearedRay* sheared, const Vec3f* p,
                                std::uint32_t id, __m128 active, Hit4& hit) {
    const __m128 zero = _mm_setzero_ps();
    const __m128 ax0 = _mm_sub_ps(_mm_set1_ps(p[0][r.kx]), r.ox), ay0 = _mm_sub_ps(_mm_set1_ps(p[0][r.ky]), r.oy);
    const __m128 az0 = _mm_sub_ps(_mm_set1_ps(p[0][r.kz]), r.oz);
    const __m128 bx0 = _mm_sub_ps(_mm_set1_ps(p[1][r.kx]), r.ox), by0 = _mm_sub_ps(_mm_set1_ps(p[1][r.ky]), r.oy);
    const __m128 bz0 = _mm_sub_ps(_mm_set1_ps(p[1][r.kz]), r.oz);
    const __m128 cx0 = _mm_sub_ps(_mm_set1_ps(p[2][r.kx]), r.ox), cy0 = _mm_sub_ps(_mm_set1_ps(p[2][r.ky]), r.oy);
    const __m128 cz0 = _mm_sub_ps(_mm_set1_ps(p[2][r.kz]), r.oz);
    const __m128 ax = _mm_sub_ps(ax0, _mm_mul_ps(r.sx, az0)), ay = _mm_sub_ps(ay0, _mm_mul_ps(r.sy, az0));
    const __m128 bx = _mm_sub_ps(bx0, _mm_mul_ps(r.sx, bz0)), by = _mm_sub_ps(by0, _mm_mul_ps(r.sy, bz0));
    const __m128 cx = _mm_sub_ps(cx0, _mm_mul_ps(r.sx, cz0)), cy = _mm_sub_ps(cy0, _mm_mul_ps(r.sy, cz0));
    const __m128 u = _mm_sub_ps(_mm_mul_ps(cx, by), _mm_mul_ps(cy, bx));
    const __m128 v = _mm_sub_ps(_mm_mul_ps(ax, cy), _mm_mul_ps(ay, cx));
    const __m128 w = _mm_sub_ps(_mm_mul_ps(bx, ay), _mm_mul_ps(by, ax));
    const __m128 on_edge = _mm_and_ps(
        active, _mm_or_ps(_mm_or_ps(_mm_cmpeq_ps(u, zero), _mm_cmpeq_ps(v, zero)), _mm_cmpeq_ps(w, zero)));
    const __m128 any_neg = _mm_or_ps(_mm_or_ps(_mm_cmplt_ps(u, zero), _mm_cmplt_ps(v, zero)), _mm_cmplt_ps(w, zero));
    const __m128 any_pos = _mm_or_ps(_mm_or_ps(_mm_cmpgt_ps(u, zero), _mm_cmpgt_ps(v, zero)), _mm_cmpgt_ps(w, zero));
    const __m128 det = _mm_add_ps(_mm_add_ps(u, v), w);
    __m128 valid = _mm_andnot_ps(_mm_or_ps(on_edge, _mm_and_ps(any_neg, any_pos)), active);
    valid = _mm_and_ps(valid, _mm_cmpneq_ps(det, zero));
    const int edge_mask = _mm_movemask_ps(on_edge);
    if (_mm_movemask_ps(valid) != 0) {
        const __m128 az = _mm_mul_ps(r.sz, az0), bz = _mm_mul_ps(r.sz, bz0), cz = _mm_mul_ps(r.sz, cz0);
        const __m128 t_scaled = _mm_add_ps(_mm_add_ps(_mm_mul_ps(u, az), _mm_mul_ps(v, bz)), _mm_mul_ps(w, cz));
        const __m128 sign_bit = _mm_and_ps(det, _mm_set1_ps(-0.0f));
        const __m128 abs_det = _mm_andnot_ps(_mm_set1_ps(-0.0f), det);
        const __m128 ts = _mm_xor_ps(t_scaled, sign_bit);
        valid = _mm_andnot_ps(_mm_cmplt_ps(ts, _mm_mul_ps(r.tmin, abs_det)), valid);
        valid = _mm_and_ps(valid, _mm_cmplt_ps(ts, _mm_mul_ps(hit.t, abs_det)));
        if (_mm_movemask_ps(valid) != 0) {
            const __m128 inv_det = _mm_div_ps(_mm_set1_ps(1.0f), det);
            const __m128 t = _mm_mul_ps(t_scaled, inv_det);
            valid = _mm_and_ps(valid, _mm_cmplt_ps(t, hit.t));
            valid = _mm_andnot_ps(_mm_cmplt_ps(t, r.tmin), valid);
            hit.t = _mm_or_ps(_mm_and_ps(valid, t), _mm_andnot_ps(valid, hit.t));
            hit.u = _mm_or_ps(_mm_and_ps(valid, _mm_mul_ps(v, inv_det)), _mm_andnot_ps(valid, hit.u));
            hit.v = _mm_or_ps(_mm_and_ps(valid, _mm_mul_ps(w, inv_det)), _mm_andnot_ps(valid, hit.v));
            const __m128i take = _mm_castps_si128(valid);
            hit.prim = _mm_or_si128(_mm_and_si128(take, _mm_set1_epi32(static_cast<int>(id))),
                                    _mm_andnot_si128(take, hit.prim));
        }
    }
    if (edge_mask != 0) {
        // Rare: the ray passes exactly through an edge in float. Decide in double, lane by lane.
        Hit lanes[4];
        hit.store(lanes);
        for (int k = 0; k < 4; ++k) {
            if ((edge_mask & (1 << k)) && intersect_triangle(rays[k], sheared[k], p[0], p[1], p[2], lanes[k])) {
                lanes[k].prim = id;
            }
        }
        hit = Hit4::load(lanes);
    }
}

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
    // Vectors whose four rays share a shear permutation (almost always, in a coherent
    // packet) test triangles four rays at a time.
    ShearedRay4 sheared4[V];
    bool uniform_shear[V];
    for (int v = 0; v < V; ++v) {
        const ShearedRay* s4 = sheared + 4 * v;
        const Ray* r4 = rays + 4 * v;
        uniform_shear[v] = true;
        for (int k = 1; k < 4; ++k) {
            uniform_shear[v] = uniform_shear[v] && s4[k].kx == s4[0].kx && s4[k].ky == s4[0].ky && s4[k].kz == s4[0].kz;
        }
        ShearedRay4& q = sheared4[v];
        q.kx = s4[0].kx;
        q.ky = s4[0].ky;
        q.kz = s4[0].kz;
        q.ox = _mm_setr_ps(r4[0].org[q.kx], r4[1].org[q.kx], r4[2].org[q.kx], r4[3].org[q.kx]);
        q.oy = _mm_setr_ps(r4[0].org[q.ky], r4[1].org[q.ky], r4[2].org[q.ky], r4[3].org[q.ky]);
        q.oz = _mm_setr_ps(r4[0].org[q.kz], r4[1].org[q.kz], r4[2].org[q.kz], r4[3].org[q.kz]);
        q.sx = _mm_setr_ps(s4[0].sx, s4[1].sx, s4[2].sx, s4[3].sx);
        q.sy = _mm_setr_ps(s4[0].sy, s4[1].sy, s4[2].sy, s4[3].sy);
        q.sz = _mm_setr_ps(s4[0].sz, s4[1].sz, s4[2].sz, s4[3].sz);
        q.tmin = _mm_setr_ps(r4[0].tmin, r4[1].tmin, r4[2].tmin, r4[3].tmin);
    }
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
            const std::uint32_t count = node->count();
            const std::uint32_t* ids = tree.tri_ids.data() + node->first();
            for (int v = 0; v < V; ++v) {
                const __m128 active = _mm_cmple_ps(tmin[v], tmax[v]);
                const int active_mask = _mm_movemask_ps(active);
                if (active_mask == 0) continue;
                Hit* h = hits + 4 * v;
                if (uniform_shear[v]) {
                    Hit4 h4 = Hit4::load(h);
                    for (std::uint32_t i = 0; i < count; ++i) {
                        const std::uint32_t id = ids[i];
                        const Vec3f* p = tri_vertices + 3 * static_cast<std::size_t>(id);
                        intersect_triangle4(sheared4[v], rays + 4 * v, sheared + 4 * v, p, id, active, h4);
                    }
                    triangle_tests += static_cast<std::uint64_t>(count) *
                                      static_cast<std::uint64_t>(__builtin_popcount(static_cast<unsigned>(active_mask)));
                    h4.store(h);
                    continue;
                }
                for (int k = 0; k < 4; ++k) {
                    if (!(active_mask & (1 << k))) continue;
                    for (std::uint32_t i = 0; i < count; ++i) {
                        const std::uint32_t id = ids[i];
                        ++triangle_tests;
                        const Vec3f* p = tri_vertices + 3 * static_cast<std::size_t>(id);
                        if (intersect_triangle(rays[4 * v + k], sheared[4 * v + k], p[0], p[1], p[2], h[k])) h[k].prim = id;
                    }
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
