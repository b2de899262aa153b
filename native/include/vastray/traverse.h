// Kd-tree ray traversal (Wald 2004 style, the base of paper 000 Algorithm 1).
//
// The root cell clip and every split step tolerate +0/-0 direction components: a
// direction of zero along an axis gives an infinite (never NaN) split distance unless
// the origin lies exactly on the plane, in which case both children are visited.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "vastray/isa.h"
#include "vastray/kdtree.h"
#include "vastray/triangle.h"

VASTRAY_KERNEL_BEGIN

// Clips the ray to a box; returns false on a miss. Zero direction components are
// handled explicitly so 0 * inf never produces NaN.
inline bool clip_ray_to_box(const Ray& ray, const Box3f& box, float& t0, float& t1) {
    t0 = ray.tmin;
    t1 = ray.tmax;
    for (int a = 0; a < 3; ++a) {
        const float o = ray.org[a], d = ray.dir[a];
        if (d == 0.0f) {
            if (o < box.lo[a] || o > box.hi[a]) return false;
            continue;
        }
        const float inv = 1.0f / d;
        float tn = (box.lo[a] - o) * inv, tf = (box.hi[a] - o) * inv;
        if (tn > tf) std::swap(tn, tf);
        // Widen the segment by a few ulps (pbrt's gamma(3)) so a ray that enters or
        // leaves the root box exactly at a vertex is not lost to rounding.
        tn -= std::abs(tn) * kSplitSlack;
        tf += std::abs(tf) * kSplitSlack;
        t0 = tn > t0 ? tn : t0;
        t1 = tf < t1 ? tf : t1;
        if (t0 > t1) return false;
    }
    return true;
}

// The walk of one ray through the subtree at node `index`, entered with the segment
// [tmin, tmax]. Closest hit (AnyHit = false) or any hit in [ray.tmin, hit.t) (AnyHit =
// true); `skip` is a triangle never reported (the surface a secondary ray starts on).
// Returns true when the ray is finished (an any-hit ray hit, or a hit lies inside its
// cell), false when the subtree is done and cells beyond it may still hold a nearer hit.
// traverse() walks from the root. (Packets keep a lone ray: handing it over here cost
// the AO query 0.82x, docs/native-core.md.)
template <bool AnyHit>
inline bool traverse_from(const KdTree& tree, const Vec3f* tri_vertices, const Ray& ray, const ShearedRay& sheared,
                          std::uint32_t index, float tmin, float tmax, Hit& hit, TraversalCounters& counters,
                          std::uint32_t skip = kNoHit) {
    // Plain arrays indexed by axis: Vec3's operator[] would branch on every step.
    const float org[3] = {ray.org.x, ray.org.y, ray.org.z};
    const float inv[3] = {1.0f / ray.dir.x, 1.0f / ray.dir.y, 1.0f / ray.dir.z};
    const bool dir_negative[3] = {std::signbit(ray.dir.x), std::signbit(ray.dir.y), std::signbit(ray.dir.z)};
    struct Entry {
        std::uint32_t node;
        float tmin, tmax;
    };
    Entry stack[64];
    int top = 0;
    std::uint64_t node_visits = 0, triangle_tests = 0;  // kept in registers, published at the end
    struct Publish {
        TraversalCounters& c;
        std::uint64_t& nodes;
        std::uint64_t& tris;
        ~Publish() {
            c.node_visits += nodes;
            c.triangle_tests += tris;
        }
    } publish{counters, node_visits, triangle_tests};
    const KdNode* nodes = tree.nodes.data();
    for (;;) {
        const KdNode* node = nodes + index;
        while (!node->is_leaf()) {
            ++node_visits;
            const int axis = node->axis();
            const float split = node->split();
            const float o = org[axis];
            const float t_split = (split - o) * inv[axis];
            // Err towards visiting both children: a ray that crosses the plane at a
            // vertex or edge lying in it must not lose the cell on either side to the
            // rounding of t_split.
            // (Infinite t_split from a zero direction component gets no slack: inf - inf
            // would be NaN and send the ray everywhere.)
            const float abs_split = std::abs(t_split);
            const float slack =
                abs_split < std::numeric_limits<float>::infinity() ? abs_split * kSplitSlack : 0.0f;
            const float ts_lo = t_split - slack, ts_hi = t_split + slack;
            const bool below_first = o < split || (o == split && dir_negative[axis]);
            // Child index 0 marks an empty child (never stored, never visited).
            const std::uint32_t left = node->left_empty() ? 0u : index + 1;
            const std::uint32_t right = node->right_empty() ? 0u : index + node->right_offset();
            const std::uint32_t first = below_first ? left : right;
            const std::uint32_t second = below_first ? right : left;
            std::uint32_t next;
            if (t_split != t_split) {
                // Origin on the plane and the ray inside it: both children are relevant.
                if (second != 0 && top < 64) stack[top++] = {second, tmin, tmax};
                next = first;
            } else if (ts_lo > tmax || t_split <= 0.0f) {
                next = first;
            } else if (ts_hi < tmin) {
                next = second;
            } else if (first == 0) {
                next = second;
                tmin = std::max(tmin, ts_lo);
            } else {
                if (second != 0 && top < 64) stack[top++] = {second, std::max(tmin, ts_lo), tmax};
                next = first;
                tmax = std::min(tmax, ts_hi);
            }
            if (next == 0) break;
            index = next;
            node = nodes + index;
        }
        if (node->is_leaf()) {
            const std::uint32_t count = node->count();
            const std::uint32_t* ids = tree.tri_ids.data() + node->first();
            for (std::uint32_t i = 0; i < count; ++i) {
                const std::uint32_t id = ids[i];
                if (id == skip) continue;
                ++triangle_tests;
                const Vec3f* v = tri_vertices + 3 * static_cast<std::size_t>(id);
                if (intersect_triangle(ray, sheared, v[0], v[1], v[2], hit)) {
                    hit.prim = id;
                    if (AnyHit) return true;
                }
            }
            // A hit inside this cell cannot be beaten by cells further along the ray. The
            // cell's far end carries the split slack, so only a hit clear of that margin
            // ends the ray; one inside it may still lose to a triangle across the plane.
            if (hit.prim != kNoHit && hit.t * (1.0f + kSplitSlack) < tmax) return true;
        }
        for (;;) {
            if (top == 0) return false;
            const Entry& e = stack[--top];
            if (e.tmin > hit.t) continue;
            index = e.node;
            tmin = e.tmin;
            tmax = e.tmax;
            break;
        }
    }
}

// Closest hit (AnyHit = false) or any hit in [tmin, tmax] (AnyHit = true). `skip` is a
// triangle never reported (the surface a secondary ray starts on).
template <bool AnyHit>
inline bool traverse(const KdTree& tree, const Vec3f* tri_vertices, const Ray& ray, Hit& hit,
                     TraversalCounters& counters, std::uint32_t skip = kNoHit) {
    float tmin, tmax;
    if (tree.nodes.empty() || !clip_ray_to_box(ray, tree.bounds, tmin, tmax)) return false;
    hit.t = ray.tmax;
    hit.prim = kNoHit;
    traverse_from<AnyHit>(tree, tri_vertices, ray, ShearedRay(ray.dir), 0, tmin, tmax, hit, counters, skip);
    return hit.prim != kNoHit;
}

// Keeps up to G resumable walks going round-robin, so that while one waits for memory
// the others run: launch(g) starts the next walk in slot g (false when none is left),
// step(g) runs slot g's walk to its next stop (true when that walk is over).
template <int G, typename Launch, typename Step>
inline void walks_in_flight(Launch&& launch, Step&& step) {
    static_assert(G >= 1 && G <= 32, "walks in flight are a 32-bit mask");
    std::uint32_t live = 0;
    for (int g = 0; g < G; ++g) live |= (launch(g) ? 1u : 0u) << g;
    while (live) {
        for (int g = 0; g < G; ++g) {
            if ((live >> g & 1u) && step(g) && !launch(g)) live &= ~(1u << g);
        }
    }
}

VASTRAY_KERNEL_END
