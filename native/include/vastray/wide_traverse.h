// Secondary rays through the 8-wide BVH (wide_bvh.h): one node load tests the ray against
// eight child boxes, hit children go on a stack, leaves are tested with the same
// watertight triangle test as the kd-tree walk, so the answer (is there a triangle in
// [tmin, tmax)? which is the nearest?) is the kd-tree's.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>

#include "vastray/isa.h"
#include "vastray/kdtree.h"
#include "vastray/prefetch.h"
#include "vastray/simd.h"
#include "vastray/traverse.h"
#include "vastray/triangle.h"
#include "vastray/wide_bvh.h"

VASTRAY_KERNEL_BEGIN

// A node's boxes take vectors of up to eight lanes: the AVX-512 build tests them as the
// AVX builds do.
constexpr int kBoxLanes = simd::kWidth < WideNode::kWidth ? simd::kWidth : WideNode::kWidth;

// The slab test of one ray against a node's eight boxes, its constants set up once per
// ray: per axis the row of a node (lo or hi) the ray enters and leaves through, and 1/d
// in every lane. A zero component gives an infinite 1/d, and a ray lying in a box's plane
// then a NaN distance to it, which hits() ignores: such a ray stays in the plane, so
// that plane does not bound its segment.
struct WideBoxTest {
    using vf = simd::vfloat<kBoxLanes>;
    // 1/d scaled for the entry and the exit distances: see hits().
    vf org[3], inv_near[3], inv_far[3], tmin, tmax;
    int near_row[3], far_row[3];  // float offsets into a WideNode

    WideBoxTest() = default;
    // (ray.tmin >= 0: the batch queries clamp it, and secondary rays start at 0.)
    explicit WideBoxTest(const Ray& ray) {
        const float o[3] = {ray.org.x, ray.org.y, ray.org.z};
        const float d[3] = {ray.dir.x, ray.dir.y, ray.dir.z};
        constexpr int W = WideNode::kWidth;
        for (int a = 0; a < 3; ++a) {
            const float i = 1.0f / d[a];
            org[a] = vf::broadcast(o[a]);
            inv_near[a] = vf::broadcast(i * (1.0f - kSplitSlack));
            inv_far[a] = vf::broadcast(i * (1.0f + kSplitSlack));
            const int lo = 2 * W * a, hi = lo + W;
            near_row[a] = std::signbit(i) ? hi : lo;
            far_row[a] = std::signbit(i) ? lo : hi;
        }
        tmin = vf::broadcast(ray.tmin);
        tmax = vf::broadcast(ray.tmax);
    }

    // The children whose boxes the segment [tmin, tmax] touches, as bits. Positive
    // entry distances shrink and exit distances grow by kSplitSlack, like the kd-tree's
    // split distances, so rounding never drops a box the ray grazes (the float error of
    // (plane - o) * (1/d) is below 2 eps of it, the slack 8 eps); scaling 1/d does that
    // once per ray (Ize's robust traversal). A negative distance keeps its sign and,
    // entering, is clamped to tmin >= 0 anyway.
    // `entries`, if given, gets each child's entry distance (closest-hit walks take the
    // nearest first).
    [[gnu::always_inline]] unsigned hits(const WideNode& node, float* entries = nullptr) const {
        constexpr int W = kBoxLanes;
        const float* base = node.lo_x;
        unsigned bits = 0;
        for (int h = 0; h < WideNode::kWidth / W; ++h) {
            const int off = h * W;
            const vf nx = (vf::load(base + near_row[0] + off) - org[0]) * inv_near[0];
            const vf ny = (vf::load(base + near_row[1] + off) - org[1]) * inv_near[1];
            const vf nz = (vf::load(base + near_row[2] + off) - org[2]) * inv_near[2];
            const vf fx = (vf::load(base + far_row[0] + off) - org[0]) * inv_far[0];
            const vf fy = (vf::load(base + far_row[1] + off) - org[1]) * inv_far[1];
            const vf fz = (vf::load(base + far_row[2] + off) - org[2]) * inv_far[2];
            // min/max return their second operand when either is NaN (minps, maxps): the
            // plane distances go first, so a NaN one leaves the segment as it was.
            const vf tn = max(nx, max(ny, max(nz, tmin)));
            const vf tf = min(fx, min(fy, min(fz, tmax)));
            if (entries != nullptr) tn.store(entries + off);
            bits |= static_cast<unsigned>((tn <= tf).bits()) << off;
        }
        return bits;
    }
};

// A walk's stack: trees are at most 58 levels deep (wide_bvh_build.cpp), a level adds at
// most 7 entries.
constexpr int kWideStack = 8 * 64;

// The watertight triangle test (triangle.h) of one ray against the four triangles of a
// WideQuad at once: its constants in SSE lanes, set up once per ray.
struct QuadRay {
    using vf = simd::vfloat<WideQuad::kLanes>;
    vf org[3];  // the origin's coordinates in the sheared frame's order: kx, ky, kz
    vf sx, sy, sz, tmin, tmax;
    int kx = 0, ky = 1, kz = 2;

    QuadRay() = default;
    QuadRay(const Ray& ray, const ShearedRay& s) : kx(s.kx), ky(s.ky), kz(s.kz) {
        org[0] = vf::broadcast(ray.org[kx]);
        org[1] = vf::broadcast(ray.org[ky]);
        org[2] = vf::broadcast(ray.org[kz]);
        sx = vf::broadcast(s.sx);
        sy = vf::broadcast(s.sy);
        sz = vf::broadcast(s.sz);
        tmin = vf::broadcast(ray.tmin);
        tmax = vf::broadcast(ray.tmax);
    }
};

// The float part of intersect_triangle for the four triangles of a quad at once: each lane
// does its float operations in its order (the kernels do not contract them into FMAs), so
// a lane's values are the scalar test's. `in`: the lanes whose hit lies in [tmin, tmax)
// (with `Closed`, every lane whose t lies in [tmin, tmax], and a few beyond: quad_closest's
// candidates); `exact`: the lanes with an edge function exactly zero, which only the
// scalar test decides (in double).
template <bool Closed = false>
struct QuadTest {
    using vf = QuadRay::vf;
    vf u, v, w, det, t_scaled, ts, abs_det, inv_det, t;
    unsigned in = 0, exact = 0;

    [[gnu::always_inline]] QuadTest(const WideQuad& quad, const QuadRay& r, vf tmax) {
        // (A lambda here was not inlined.)
        const auto edge = [&](int k, vf& x, vf& y, vf& z) __attribute__((always_inline)) {
            z = vf::load(quad.v[k][r.kz]) - r.org[2];
            x = (vf::load(quad.v[k][r.kx]) - r.org[0]) - r.sx * z;
            y = (vf::load(quad.v[k][r.ky]) - r.org[1]) - r.sy * z;
        };
        vf ax, ay, az, bx, by, bz, cx, cy, cz;
        edge(0, ax, ay, az);
        edge(1, bx, by, bz);
        edge(2, cx, cy, cz);
        u = cx * by - cy * bx;
        v = ax * cy - ay * cx;
        w = bx * ay - by * ax;
        const vf zero = vf::broadcast(0.0f);
        exact = static_cast<unsigned>(((u == zero) | (v == zero) | (w == zero)).bits());
        const auto negative = (u < zero) | (v < zero) | (w < zero);
        const auto positive = (u > zero) | (v > zero) | (w > zero);
        det = u + v + w;
        t_scaled = u * (r.sz * az) + v * (r.sz * bz) + w * (r.sz * cz);
        // t_scaled * sign(det) and |det|, compared without dividing, then t itself.
        ts = t_scaled ^ simd::sign_bits(det);
        abs_det = simd::abs(det);
        inv_det = vf::broadcast(1.0f) / det;
        t = t_scaled * inv_det;
        const auto below = Closed ? (ts <= tmax * abs_det) | (t <= tmax) : (ts < tmax * abs_det) & (t < tmax);
        const auto after_tmin = andnot(ts < r.tmin * abs_det, below) & andnot(t < r.tmin, below);
        in = static_cast<unsigned>((andnot(negative & positive, det != zero) & after_tmin).bits());
    }
};

// The first `count` lanes of a quad, less those whose triangle is `skip`.
[[gnu::always_inline]] inline unsigned quad_lanes(const WideQuad& quad, std::uint32_t count, std::uint32_t skip) {
    unsigned lanes = (1u << count) - 1;
    for (int lane = 0; lane < WideQuad::kLanes; ++lane) {
        if (quad.prim[lane] == skip) lanes &= ~(1u << lane);
    }
    return lanes;
}

// Whether one of the first `count` triangles of `quad` other than `skip` lies on the ray
// in [tmin, tmax): the scalar test's answer.
[[gnu::always_inline]] inline bool quad_hit(const WideQuad& quad, std::uint32_t count, const QuadRay& r,
                                            const Ray& ray, const ShearedRay& sheared, std::uint32_t skip) {
    const unsigned lanes = quad_lanes(quad, count, skip);
    const QuadTest<> q(quad, r, r.tmax);
    if ((q.in & lanes & ~q.exact) != 0) return true;
    for (unsigned e = q.exact & lanes; e != 0; e &= e - 1) {
        const int lane = __builtin_ctz(e);
        Hit hit;
        hit.t = ray.tmax;
        if (intersect_triangle(ray, sheared, quad.corner(lane, 0), quad.corner(lane, 1), quad.corner(lane, 2), hit)) {
            return true;
        }
    }
    return false;
}

// Whether a hit at t on triangle `prim` replaces `hit`: it is nearer, or as near and of a
// lower index. That is a strict order on (t, index), so every walk of the wide BVH (one
// ray, a packet, in flight or not) gives a ray the same answer whatever order it meets
// the triangles in: a walk skips a box only when it starts beyond the hit, so it meets
// every triangle that could win.
[[gnu::always_inline]] inline bool wins(float t, std::uint32_t prim, const Hit& hit) {
    return t < hit.t || (t == hit.t && hit.prim != kNoHit && prim < hit.prim);
}

// The winner (wins) among `hit` and the first `count` triangles of `quad` other than
// `skip` that intersect_triangle finds on the ray in [tmin, tmax): `hit` gets it (t, u, v
// and prim); false if it stays. (The scalar test also compares its t with the hit so far
// in a second form, t_scaled against hit.t * |det|, which makes its answer depend on the
// order of the triangles; here only a triangle's own range test uses that form.)
[[gnu::always_inline]] inline bool quad_closest(const WideQuad& quad, std::uint32_t count, const QuadRay& r,
                                                const Ray& ray, const ShearedRay& sheared, std::uint32_t skip,
                                                Hit& hit) {
    using vf = QuadRay::vf;
    const unsigned lanes = quad_lanes(quad, count, skip);
    // Candidates: every lane with t <= hit.t (and some beyond it), in the ray's range.
    const QuadTest<true> q(quad, r, vf::broadcast(hit.t));
    unsigned candidates = (q.in | q.exact) & lanes;
    if (candidates == 0) return false;
    alignas(16) float t[WideQuad::kLanes], ts[WideQuad::kLanes], abs_det[WideQuad::kLanes], u[WideQuad::kLanes],
        v[WideQuad::kLanes];
    q.t.store(t);
    q.ts.store(ts);
    q.abs_det.store(abs_det);
    (q.v * q.inv_det).store(u);
    (q.w * q.inv_det).store(v);
    bool found = false;
    for (; candidates != 0; candidates &= candidates - 1) {
        const int lane = __builtin_ctz(candidates);
        const std::uint32_t prim = quad.prim[lane];
        if (q.exact >> lane & 1u) {
            Hit h;
            h.t = ray.tmax;
            if (intersect_triangle(ray, sheared, quad.corner(lane, 0), quad.corner(lane, 1), quad.corner(lane, 2), h) &&
                wins(h.t, prim, hit)) {
                hit.t = h.t;
                hit.u = h.u;
                hit.v = h.v;
                hit.prim = prim;
                found = true;
            }
        } else if (ts[lane] < ray.tmax * abs_det[lane] && t[lane] < ray.tmax && wins(t[lane], prim, hit)) {
            hit.t = t[lane];
            hit.u = u[lane];
            hit.v = v[lane];
            hit.prim = prim;
            found = true;
        }
    }
    return found;
}

// Whether a triangle of the leaf `code` other than `skip` lies on the ray in [tmin, tmax).
[[gnu::always_inline]] inline bool wide_leaf_hit(const WideBvh& bvh, std::uint32_t code, const QuadRay& r,
                                                 const Ray& ray, const ShearedRay& sheared, std::uint32_t skip,
                                                 std::uint64_t& triangle_tests) {
    const WideQuad* quad = bvh.quads.data() + WideNode::leaf_first(code);
    std::uint32_t count = WideNode::leaf_count(code);
    triangle_tests += count;
    for (;; ++quad, count -= WideQuad::kLanes) {
        if (count <= WideQuad::kLanes) return quad_hit(*quad, count, r, ray, sheared, skip);
        if (quad_hit(*quad, WideQuad::kLanes, r, ray, sheared, skip)) return true;
    }
}

// A node's step, the same in every walk (so all count the same visits): its first hit
// child becomes `cur`, the others go on the stack in slot order. False: no child was hit.
[[gnu::always_inline]] inline bool wide_descend(const WideNode& node, const WideBoxTest& test, std::uint32_t& cur,
                                                std::uint32_t* stack, int& top) {
    unsigned bits = test.hits(node);
    if (bits == 0) return false;
    cur = node.child[__builtin_ctz(bits)];
    for (bits &= bits - 1; bits != 0; bits &= bits - 1) stack[top++] = node.child[__builtin_ctz(bits)];
    return true;
}

// What a walk resumable at each node or leaf it is about to load keeps of its ray, so
// several can run in turn and each one's next load is on its way while the others work
// (the kd walks do the same: walks_in_flight). The load it stops before is prefetched.
struct WideWalkRay {
    Ray ray;
    WideBoxTest test;
    ShearedRay sheared;
    QuadRay quad_ray;
    std::uint32_t skip = kNoHit;
    std::uint32_t cur = 0;
    int top = 0;

    void begin(const Ray& ray_in, std::uint32_t skip_prim) {
        ray = ray_in;
        test = WideBoxTest(ray_in);
        sheared = ShearedRay(ray_in.dir);
        quad_ray = QuadRay(ray_in, sheared);
        skip = skip_prim;
        cur = 0;
        top = 0;
    }

    static void prefetch(const WideBvh& bvh, std::uint32_t code) {
        if (WideNode::is_leaf(code)) {
            // Every line of the leaf's quads (3 lines for one).
            const auto* first = reinterpret_cast<const char*>(bvh.quads.data() + WideNode::leaf_first(code));
            const char* last = first + WideQuad::count_for(WideNode::leaf_count(code)) * sizeof(WideQuad) - 1;
            const auto line = [](const char* p) { return reinterpret_cast<std::uintptr_t>(p) >> 6; };
            for (const char* p = first; line(p) <= line(last); p += 64) prefetch_line(p);
        } else {
            const char* n = reinterpret_cast<const char*>(bvh.nodes.data() + code);
            prefetch_line(n);
            prefetch_line(n + 64);
            prefetch_line(n + 128);
            prefetch_line(n + 192);
        }
    }
};

// One any-hit walk, resumable (WideWalkRay).
struct WideWalk : WideWalkRay {
    bool occluded = false;
    std::uint32_t stack[kWideStack];

    void start(const Ray& ray_in, std::uint32_t skip_prim = kNoHit) {
        begin(ray_in, skip_prim);
        occluded = false;
    }

    // Visits `cur`; returns true when the walk is over (occluded says how).
    bool step(const WideBvh& bvh, std::uint64_t& node_visits, std::uint64_t& triangle_tests) {
        if (WideNode::is_leaf(cur)) {
            if (wide_leaf_hit(bvh, cur, quad_ray, ray, sheared, skip, triangle_tests)) {
                occluded = true;
                return true;
            }
        } else {
            ++node_visits;
            if (wide_descend(bvh.nodes[cur], test, cur, stack, top)) {
                prefetch(bvh, cur);
                return false;
            }
        }
        if (top == 0) return true;
        cur = stack[--top];
        prefetch(bvh, cur);
        return false;
    }
};

// The triangle test's constants of a single walk, made at its first leaf (sheared_set
// says whether they are there yet): many rays leave the tree without reaching one.
inline void shear_once(const Ray& ray, bool& sheared_set, ShearedRay& sheared, QuadRay& quad_ray) {
    if (sheared_set) return;
    sheared = ShearedRay(ray.dir);
    quad_ray = QuadRay(ray, sheared);
    sheared_set = true;
}

// Is there a triangle (other than `skip`) in [ray.tmin, ray.tmax)? One walk to its end,
// its state in registers; a node's first hit child is walked next without a push.
inline bool occluded_wide(const WideBvh& bvh, const Ray& ray, TraversalCounters& counters,
                          std::uint32_t skip = kNoHit) {
    const WideBoxTest test(ray);
    // The triangle test's constants (three more divisions) wait for the first leaf: many
    // rays leave the tree without reaching one.
    ShearedRay sheared;
    QuadRay quad_ray;
    bool sheared_set = false;
    std::uint32_t stack[kWideStack];
    int top = 0;
    std::uint32_t cur = 0;
    std::uint64_t node_visits = 0, triangle_tests = 0;
    bool occluded = false;
    for (;;) {
        if (!WideNode::is_leaf(cur)) {
            ++node_visits;
            if (wide_descend(bvh.nodes[cur], test, cur, stack, top)) continue;
        } else {
            shear_once(ray, sheared_set, sheared, quad_ray);
            if (wide_leaf_hit(bvh, cur, quad_ray, ray, sheared, skip, triangle_tests)) {
                occluded = true;
                break;
            }
        }
        if (top == 0) break;
        cur = stack[--top];
    }
    counters.node_visits += node_visits;
    counters.triangle_tests += triangle_tests;
    return occluded;
}

// A closest-hit walk's stack entry: a child and where the ray enters its box.
struct WideEntry {
    std::uint32_t code;
    float t;
};

// A closest-hit walk's node step: the node's hit children nearest first, the nearest
// becoming `cur` and the others pushed farthest first (an insertion into the stack's
// top), so pops take them in order. False: no child was hit.
[[gnu::always_inline]] inline bool wide_descend_nearest(const WideNode& node, const WideBoxTest& test,
                                                        std::uint32_t& cur, WideEntry* stack, int& top) {
    alignas(32) float entry[WideNode::kWidth];
    unsigned bits = test.hits(node, entry);
    if (bits == 0) return false;
    if ((bits & (bits - 1)) == 0) {
        cur = node.child[__builtin_ctz(bits)];
        return true;
    }
    const int first = top;
    for (; bits != 0; bits &= bits - 1) {
        const int k = __builtin_ctz(bits);
        const WideEntry e{node.child[k], entry[k]};
        int j = top++;
        for (; j > first && stack[j - 1].t < e.t; --j) stack[j] = stack[j - 1];
        stack[j] = e;
    }
    cur = stack[--top].code;
    return true;
}

// A leaf's quads in order for a closest hit (quad_closest); true when `hit` moved.
[[gnu::always_inline]] inline bool wide_leaf_nearest(const WideBvh& bvh, std::uint32_t code, const QuadRay& r,
                                                     const Ray& ray, const ShearedRay& sheared, std::uint32_t skip,
                                                     Hit& hit, std::uint64_t& triangle_tests) {
    const WideQuad* quad = bvh.quads.data() + WideNode::leaf_first(code);
    std::uint32_t count = WideNode::leaf_count(code);
    triangle_tests += count;
    bool found = false;
    for (;; ++quad, count -= WideQuad::kLanes) {
        const std::uint32_t n = count < WideQuad::kLanes ? count : WideQuad::kLanes;
        found |= quad_closest(*quad, n, r, ray, sheared, skip, hit);
        if (count <= WideQuad::kLanes) break;
    }
    return found;
}

// wide_leaf_nearest for a single walk: on a nearer hit the box test's segment ends there,
// so boxes beyond it are no longer entered.
[[gnu::always_inline]] inline void wide_leaf_closest(const WideBvh& bvh, std::uint32_t code, const QuadRay& r,
                                                     const Ray& ray, const ShearedRay& sheared, std::uint32_t skip,
                                                     Hit& hit, WideBoxTest& test, std::uint64_t& triangle_tests) {
    if (wide_leaf_nearest(bvh, code, r, ray, sheared, skip, hit, triangle_tests)) {
        test.tmax = WideBoxTest::vf::broadcast(hit.t);
    }
}

// The next child to visit: the top entry that starts before the hit; false when none is
// left.
[[gnu::always_inline]] inline bool wide_pop_nearer(const WideEntry* stack, int& top, float hit_t,
                                                   std::uint32_t& cur) {
    while (top > 0 && stack[top - 1].t > hit_t) --top;
    if (top == 0) return false;
    cur = stack[--top].code;
    return true;
}

// The closest triangle (other than `skip`) in [ray.tmin, ray.tmax): the indirect mode's
// diffuse rays, which start anywhere on the model in any direction. One walk to its end,
// its state in registers; a node's hit children are taken nearest first, a hit shortens
// the box tests, and a popped child that starts beyond the hit is skipped. The answer is
// the nearest triangle, of two at the same t the lower index (quad_closest), whatever the
// order of the walk; the kd-tree walk keeps the first it tests of two such, and of two
// triangles nearly as near (where intersect_triangle's two comparisons disagree) the one
// it tests first, so the two differ on a few pixels in a million.
inline void closest_wide(const WideBvh& bvh, const Ray& ray, Hit& hit, TraversalCounters& counters,
                         std::uint32_t skip = kNoHit) {
    WideBoxTest test(ray);
    hit.t = ray.tmax;
    hit.prim = kNoHit;
    ShearedRay sheared;  // (set at the first leaf, as in occluded_wide)
    QuadRay quad_ray;
    bool sheared_set = false;
    WideEntry stack[kWideStack];
    int top = 0;
    std::uint32_t cur = 0;
    std::uint64_t node_visits = 0, triangle_tests = 0;
    for (;;) {
        if (!WideNode::is_leaf(cur)) {
            ++node_visits;
            if (wide_descend_nearest(bvh.nodes[cur], test, cur, stack, top)) continue;
        } else {
            shear_once(ray, sheared_set, sheared, quad_ray);
            wide_leaf_closest(bvh, cur, quad_ray, ray, sheared, skip, hit, test, triangle_tests);
        }
        if (!wide_pop_nearer(stack, top, hit.t, cur)) break;
    }
    counters.node_visits += node_visits;
    counters.triangle_tests += triangle_tests;
}

// closest_wide as a walk resumable (WideWalkRay), for walks in flight on a large tree.
struct WideClosestWalk : WideWalkRay {
    Hit* hit = nullptr;
    WideEntry stack[kWideStack];

    void start(const Ray& ray_in, Hit& hit_out, std::uint32_t skip_prim) {
        begin(ray_in, skip_prim);
        hit = &hit_out;
        hit->t = ray_in.tmax;
        hit->prim = kNoHit;
    }

    // Goes on with a ray's walk below node `code`, its closest hit so far in `hit_out` (a
    // packet's ray left alone in a subtree, wide_traverse_packet.h).
    void resume(const Ray& ray_in, Hit& hit_out, std::uint32_t code) {
        begin(ray_in, kNoHit);
        hit = &hit_out;
        test.tmax = WideBoxTest::vf::broadcast(hit_out.t);
        cur = code;
    }

    // Visits `cur`; true when the walk is over (*hit is its answer).
    bool step(const WideBvh& bvh, std::uint64_t& node_visits, std::uint64_t& triangle_tests) {
        if (WideNode::is_leaf(cur)) {
            wide_leaf_closest(bvh, cur, quad_ray, ray, sheared, skip, *hit, test, triangle_tests);
        } else {
            ++node_visits;
            if (wide_descend_nearest(bvh.nodes[cur], test, cur, stack, top)) {
                prefetch(bvh, cur);
                return false;
            }
        }
        if (!wide_pop_nearer(stack, top, hit->t, cur)) return true;
        prefetch(bvh, cur);
        return false;
    }
};

// Walks in flight take their rays in order: starts the next ray that ray_of(i, ray, skip)
// gives from `next` on with start(i, ray, skip); false when none is left.
template <typename RayOf, typename Start>
[[gnu::always_inline]] inline bool start_next_ray(std::size_t& next, std::size_t count, RayOf& ray_of,
                                                  Start&& start) {
    Ray ray;
    std::uint32_t skip = kNoHit;
    for (; next < count; ++next) {
        if (!ray_of(next, ray, skip)) continue;
        start(next++, ray, skip);
        return true;
    }
    return false;
}

// Closest hits of `count` rays, G walks in flight: ray_of(i, ray, skip) sets ray i and
// the triangle it must not report (false: no ray), hit_of(i) is where its hit goes. The
// answers are closest_wide's.
template <int G, typename RayOf, typename HitOf>
inline void closest_wide_in_flight(const WideBvh& bvh, std::size_t count, RayOf&& ray_of, HitOf&& hit_of,
                                   TraversalCounters& counters) {
    WideClosestWalk walks[G];
    std::size_t next = 0;
    std::uint64_t node_visits = 0, triangle_tests = 0;
    walks_in_flight<G>(
        [&](int g) {
            return start_next_ray(next, count, ray_of, [&](std::size_t i, const Ray& ray, std::uint32_t skip) {
                walks[g].start(ray, hit_of(i), skip);
            });
        },
        [&](int g) { return walks[g].step(bvh, node_visits, triangle_tests); });
    counters.node_visits += node_visits;
    counters.triangle_tests += triangle_tests;
}

// Any hits of `count` rays, G walks in flight: ray_of(i, ray, skip) sets ray i and the
// triangle it must not report (false: no ray, no answer), answer(i) is called for each
// ray that is occluded.
template <int G, typename RayOf, typename Answer>
inline void occluded_wide_in_flight(const WideBvh& bvh, std::size_t count, RayOf&& ray_of, Answer&& answer,
                                    TraversalCounters& counters) {
    WideWalk walks[G];
    std::size_t id[G];
    std::size_t next = 0;
    std::uint64_t node_visits = 0, triangle_tests = 0;
    walks_in_flight<G>(
        [&](int g) {
            return start_next_ray(next, count, ray_of, [&](std::size_t i, const Ray& ray, std::uint32_t skip) {
                walks[g].start(ray, skip);
                id[g] = i;
            });
        },
        [&](int g) {
            if (!walks[g].step(bvh, node_visits, triangle_tests)) return false;
            if (walks[g].occluded) answer(id[g]);
            return true;
        });
    counters.node_visits += node_visits;
    counters.triangle_tests += triangle_tests;
}

VASTRAY_KERNEL_END
