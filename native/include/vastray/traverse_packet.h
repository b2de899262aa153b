// Ray-packet traversal of the in-core kd-tree (Wald 2004), for coherent rays such as
// the primary rays of a pixel block. A packet of N rays (16: a 4x4 block, 4: a 2x2
// quad) lives in N / W SIMD vectors of W lanes (packet.h: 4 with SSE, 8 with AVX). One
// node fetch and one decision serve the packet; per-ray segments [tmin, tmax] stay in
// registers, and a ray whose segment is empty stops influencing decisions. Leaves test
// one triangle against W rays with the float operations of the scalar watertight test,
// so packets change speed, never answers.
//
// Preconditions (packet_is_coherent): every direction component is non-zero and has the
// same sign across the packet, so all rays order the children alike.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

#include "vastray/isa.h"
#include "vastray/prefetch.h"
#include "vastray/packet.h"
#include "vastray/traverse.h"

VASTRAY_KERNEL_BEGIN

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

// clip_ray_to_box for the W rays of one vector at once, with the same float operations on
// each lane, so the same segments: the per-ray calls, three divisions each, were 1.5 % of
// an in-core frame. t0 and t1 come in as the rays' tmin and tmax and leave as their
// segments; a lane outside `in`, or one that misses the box, gets the empty segment
// [inf, -inf]. Clipping only narrows, so one emptiness test at the end equals the scalar
// test after each axis. Returns the lanes that enter the box.
template <int W>
inline simd::vmask<W> clip_rays_to_box(const Box3f& box, const simd::vfloat<W> (&o)[3],
                                       const simd::vfloat<W> (&d)[3], simd::vfloat<W>& t0, simd::vfloat<W>& t1,
                                       simd::vmask<W> in) {
    using vf = simd::vfloat<W>;
    constexpr float kInf = std::numeric_limits<float>::infinity();
    const vf slack = vf::broadcast(kSplitSlack), one = vf::broadcast(1.0f), zero = vf::broadcast(0.0f);
    for (int a = 0; a < 3; ++a) {
        const vf lo = vf::broadcast(box.lo[a]), hi = vf::broadcast(box.hi[a]);
        // A zero component: the origin must lie in the slab, and the axis clips nothing.
        const simd::vmask<W> flat = d[a] == zero;
        in = andnot(flat & ((o[a] < lo) | (o[a] > hi)), in);
        const vf inv = one / d[a];
        const vf tn = (lo - o[a]) * inv, tf = (hi - o[a]) * inv;
        const simd::vmask<W> swap = tn > tf;
        const vf near = select(swap, tf, tn), far = select(swap, tn, tf);
        const vf wide_near = near - abs(near) * slack, wide_far = far + abs(far) * slack;
        t0 = select(flat, t0, select(wide_near > t0, wide_near, t0));
        t1 = select(flat, t1, select(wide_far < t1, wide_far, t1));
    }
    in = andnot(t0 > t1, in);
    t0 = select(in, t0, vf::broadcast(kInf));
    t1 = select(in, t1, vf::broadcast(-kInf));
    return in;
}

// Vector v of a packet's origins and directions (component arrays), and the origin and
// reciprocal direction vectors its walk keeps.
template <int W, int N, int K>
inline void load_ray_vectors(const float (&o)[3][N], const float (&d)[3][N], int v, simd::vfloat<W> (&ov)[3],
                             simd::vfloat<W> (&dv)[3], simd::vfloat<W> (&org)[3][K], simd::vfloat<W> (&inv)[3][K]) {
    for (int a = 0; a < 3; ++a) {
        ov[a] = simd::vfloat<W>::load(o[a] + W * v);
        dv[a] = simd::vfloat<W>::load(d[a] + W * v);
        org[a][v] = ov[a];
        inv[a][v] = simd::vfloat<W>::broadcast(1.0f) / dv[a];
    }
}

// Whether a walk stepping from node `from` to `to` will find it in cache: the next node in
// memory (a left child, whose line the hardware has most likely brought along), or any
// node on the same 64-byte line (near the leaves a right child often is). Only other
// steps are worth a pause for their load.
inline bool near_in_memory(const KdNode* from, const KdNode* to) {
    return to == from + 1 || reinterpret_cast<std::uintptr_t>(from) >> 6 == reinterpret_cast<std::uintptr_t>(to) >> 6;
}

// Asks for the vertices of a leaf's first triangles (leaves hold a few), whose ids are
// at hand: what a walk in flight does before it pauses for a leaf's tests.
// (GCC 12 once dropped every call to it, so that the walks paused for vertices nobody
// had asked for: prefetch.h says why, and why it cannot happen again.)
[[gnu::always_inline]] inline void prefetch_leaf_vertices(const KdTree& tree, const Vec3f* tri_vertices,
                                                          const KdNode& leaf) {
    constexpr std::uint32_t kPrefetchTriangles = 8;
    const std::uint32_t* ids = tree.tri_ids.data() + leaf.first();
    const std::uint32_t count = std::min<std::uint32_t>(leaf.count(), kPrefetchTriangles);
    for (std::uint32_t i = 0; i < count; ++i) {
        const char* p = reinterpret_cast<const char*>(tri_vertices + 3 * static_cast<std::size_t>(ids[i]));
        prefetch_line(p);
        prefetch_line(p + 3 * sizeof(Vec3f) - 1);
    }
}

namespace kd_detail {

// The closest-hit walk of one packet as an object. With Yield it stops where its next
// load would likely miss (a jump to a node that is not the next in memory, a leaf's id
// list, its vertices), having prefetched it, so that a caller with several packets in
// flight (traverse_packets) runs the others meanwhile and their misses overlap. Without
// it run() goes to the end in one call: that is traverse_packet(). Either way each ray
// does the same arithmetic in the same order.
template <int N, bool Yield>
class PacketWalker {
    static constexpr int W = packet_width<N>();
    static constexpr int K = N / W;
    using vf = simd::vfloat<W>;
    using vm = simd::vmask<W>;

public:
    // Sets up the packet of N coherent rays in row order, whose hits go to hits_out.
    // False when no ray enters the tree: hits_out is then already written.
    bool start(const KdTree& tree, const Ray* rays_in, Hit* hits_out) {
        hits_out_ = hits_out;
        for (int i = 0; i < N; ++i) rays_[packet_lane<N, W>(i)] = rays_in[i];
        alignas(32) float o[3][N], d[3][N], ray_t0[N], ray_t1[N];
        for (int k = 0; k < N; ++k) {
            hits_[k] = Hit{};
            hits_[k].t = rays_[k].tmax;
            ray_t0[k] = rays_[k].tmin;
            ray_t1[k] = rays_[k].tmax;
            for (int a = 0; a < 3; ++a) {
                o[a][k] = rays_[k].org[a];
                d[a][k] = rays_[k].dir[a];
            }
        }
        int entered = 0;
        for (int v = 0; v < K; ++v) {
            vf ov[3], dv[3];
            load_ray_vectors(o, d, v, ov, dv, org_, inv_);
            vf t0 = vf::load(ray_t0 + W * v), t1 = vf::load(ray_t1 + W * v);
            hit_t_[v] = t1;
            entered |= clip_rays_to_box<W>(tree.bounds, ov, dv, t0, t1, vm::from_bits((1u << W) - 1u)).bits();
            tmin_[v] = t0;
            tmax_[v] = t1;
        }
        if (!entered) {
            finish();
            return false;
        }
        // Shear constants once per ray, not once per leaf visit.
        for (int k = 0; k < N; ++k) sheared_[k] = ShearedRay(rays_[k].dir);
        for (int v = 0; v < K; ++v) sheared_v_[v] = ShearedRayV<W>(rays_ + W * v, sheared_ + W * v);
        // With equal signs, "below first" is the same for every ray of the packet.
        for (int a = 0; a < 3; ++a) below_first_[a] = !std::signbit(rays_[0].dir[a]);
        index_ = 0;
        top_ = 0;
        stage_ = Stage::Descend;
        return true;
    }

    // Walks on; true when the walk is over and hits_out is written.
    bool run(const KdTree& tree, const Vec3f* tri_vertices, std::uint64_t& node_visits,
             std::uint64_t& triangle_tests) {
        const KdNode* nodes = tree.nodes.data();
        const vf slack_scale = vf::broadcast(kSplitSlack);
        vf tmin[K], tmax[K];
        for (int v = 0; v < K; ++v) {
            tmin[v] = tmin_[v];
            tmax[v] = tmax_[v];
        }
        std::uint32_t index = index_;
        int top = top_;
        // Keeps the position for the next call (Yield only).
        auto pause = [&](Stage next) {
            for (int v = 0; v < K; ++v) {
                tmin_[v] = tmin[v];
                tmax_[v] = tmax[v];
            }
            index_ = index;
            top_ = top;
            stage_ = next;
            return false;
        };
        for (;;) {
            bool at_leaf = true;
            if (stage_ == Stage::Descend) {
                const KdNode* node = nodes + index;
                while (!node->is_leaf()) {
                    ++node_visits;
                    const int axis = node->axis();
                    const vf split = vf::broadcast(node->split());
                    const std::uint32_t left = node->left_empty() ? 0u : index + 1;
                    const std::uint32_t right = node->right_empty() ? 0u : index + node->right_offset();
                    const std::uint32_t near_child = below_first_[axis] ? left : right;
                    const std::uint32_t far_child = below_first_[axis] ? right : left;
                    // Each ray's part of its segment on either side of the plane, overlapping
                    // by the same slack as single rays; an empty part (tmin > tmax) makes the
                    // ray inactive in that child.
                    vf near_tmax[K], far_tmin[K];
                    int near_mask = 0, far_mask = 0;
                    for (int v = 0; v < K; ++v) {
                        const vf t_split = (split - org_[axis][v]) * inv_[axis][v];
                        const vf slack = abs(t_split) * slack_scale;
                        near_tmax[v] = min(t_split + slack, tmax[v]);
                        far_tmin[v] = max(t_split - slack, tmin[v]);
                        near_mask |= (tmin[v] <= near_tmax[v]).bits();
                        far_mask |= (far_tmin[v] <= tmax[v]).bits();
                    }
                    const bool near_active = near_child != 0 && near_mask != 0;
                    const bool far_active = far_child != 0 && far_mask != 0;
                    const std::uint32_t from = index;
                    if (near_active) {
                        if (far_active && top < kStack) {
                            for (int v = 0; v < K; ++v) {
                                stack_[top].tmin[v] = far_tmin[v];
                                stack_[top].tmax[v] = tmax[v];
                            }
                            stack_[top].node = far_child;
                            ++top;
                            // Wanted when the near subtree is done: its line arrives meanwhile.
                            if constexpr (Yield) prefetch_line(nodes + far_child);
                        }
                        for (int v = 0; v < K; ++v) tmax[v] = near_tmax[v];
                        index = near_child;
                    } else if (far_active) {
                        for (int v = 0; v < K; ++v) tmin[v] = far_tmin[v];
                        index = far_child;
                    } else {
                        at_leaf = false;
                        break;
                    }
                    node = nodes + index;
                    if constexpr (Yield) {
                        if (!near_in_memory(nodes + from, node)) {
                            prefetch_line(node);
                            return pause(Stage::Descend);
                        }
                    }
                }
                if (at_leaf) {
                    if constexpr (Yield) {
                        prefetch_line(tree.tri_ids.data() + node->first());
                        return pause(Stage::LeafIds);
                    }
                    stage_ = Stage::LeafTest;
                }
            } else if (stage_ == Stage::LeafIds) {
                prefetch_leaf_vertices(tree, tri_vertices, nodes[index]);
                // And wait for them: tests right after the prefetch stalled on these loads
                // (a fifth of a 10^7 mandelbulb frame, at the first vertex's load).
                if constexpr (Yield) return pause(Stage::LeafTest);
                stage_ = Stage::LeafTest;
            }
            if (at_leaf && stage_ == Stage::LeafTest) {
                const KdNode* node = nodes + index;
                const std::uint32_t count = node->count();
                const std::uint32_t* ids = tree.tri_ids.data() + node->first();
                for (int v = 0; v < K; ++v) {
                    const vm active = tmin[v] <= tmax[v];
                    const int active_mask = active.bits();
                    if (active_mask == 0) continue;
                    Hit* h = hits_ + W * v;
                    HitV<W> hv = HitV<W>::load(h);
                    for (std::uint32_t i = 0; i < count; ++i) {
                        const std::uint32_t id = ids[i];
                        const Vec3f* p = tri_vertices + 3 * static_cast<std::size_t>(id);
                        intersect_triangle_v<W>(sheared_v_[v], rays_ + W * v, sheared_ + W * v, p[0], p[1], p[2], id,
                                                active, hv);
                    }
                    triangle_tests += static_cast<std::uint64_t>(count) *
                                      static_cast<std::uint64_t>(__builtin_popcount(static_cast<unsigned>(active_mask)));
                    hv.store(h);
                    hit_t_[v] = hv.t;
                }
            }
            // Pop the next subtree in which some ray still has a segment before its hit.
            // Clipping each segment to the ray's hit retires rays that are finished, the
            // packet form of the single-ray early exit.
            for (;;) {
                if (top == 0) {
                    finish();
                    return true;
                }
                --top;
                int active = 0;
                for (int v = 0; v < K; ++v) {
                    tmin[v] = stack_[top].tmin[v];
                    tmax[v] = min(stack_[top].tmax[v], hit_t_[v]);
                    active |= (tmin[v] <= tmax[v]).bits();
                }
                if (active != 0) {
                    index = stack_[top].node;
                    break;
                }
            }
            stage_ = Stage::Descend;
        }
    }

private:
    enum class Stage : std::uint8_t { Descend, LeafIds, LeafTest };
    struct Entry {
        vf tmin[K], tmax[K];
        std::uint32_t node;
    };
    static constexpr int kStack = 64;

    void finish() {
        for (int i = 0; i < N; ++i) hits_out_[i] = hits_[packet_lane<N, W>(i)];
    }

    Ray rays_[N];
    Hit hits_[N];
    ShearedRay sheared_[N];
    ShearedRayV<W> sheared_v_[K];
    vf org_[3][K], inv_[3][K];
    vf tmin_[K], tmax_[K], hit_t_[K];
    bool below_first_[3];
    Stage stage_ = Stage::Descend;
    std::uint32_t index_ = 0;
    int top_ = 0;
    Hit* hits_out_ = nullptr;
    Entry stack_[kStack];
};

}  // namespace kd_detail

// Closest hits of N coherent rays given in row order; hits[i] gets ray i's result.
template <int N>
inline void traverse_packet(const KdTree& tree, const Vec3f* tri_vertices, const Ray* rays_in, Hit* hits_out,
                            TraversalCounters& counters) {
    kd_detail::PacketWalker<N, false> walker;
    if (!walker.start(tree, rays_in, hits_out)) return;
    std::uint64_t node_visits = 0, triangle_tests = 0;
    walker.run(tree, tri_vertices, node_visits, triangle_tests);
    counters.node_visits += node_visits;
    counters.triangle_tests += triangle_tests;
}

// Closest hits of `count` packets of N coherent rays each (rays[j], hits[j] as in
// traverse_packet), G of them in flight at once: while one waits for a node, a leaf's
// list or its vertices, the others go on. The same answers as traverse_packet.
template <int N, int G>
inline void traverse_packets(const KdTree& tree, const Vec3f* tri_vertices, const Ray* const* rays,
                             Hit* const* hits, int count, TraversalCounters& counters) {
    kd_detail::PacketWalker<N, true> walkers[G];
    std::uint64_t node_visits = 0, triangle_tests = 0;
    int next = 0;
    walks_in_flight<G>(
        [&](int g) {
            while (next < count) {
                const int j = next++;
                if (walkers[g].start(tree, rays[j], hits[j])) return true;
            }
            return false;
        },
        [&](int g) { return walkers[g].run(tree, tri_vertices, node_visits, triangle_tests); });
    counters.node_visits += node_visits;
    counters.triangle_tests += triangle_tests;
}

namespace kd_detail {

// occluded_packet's walk as an object, as PacketWalker is traverse_packet's: with Yield
// it stops where its next load would likely miss, having prefetched it, for a caller
// with several packets in flight (occluded_packets); without, run() goes to the end.
template <int N, bool Yield>
class OcclusionWalker {
    static_assert(N <= 32, "ray masks are 32-bit");
    static constexpr int W = packet_width<N>();
    static constexpr int K = N / W;
    using vf = simd::vfloat<W>;
    using vm = simd::vmask<W>;

public:
    // The rays (lane order), skip ids and mask stay the caller's until the walk is over.
    // False when no ray of `mask` enters the tree (the answer is then 0).
    bool start(const KdTree& tree, const Ray* rays, const std::uint32_t* skip, std::uint32_t mask) {
        rays_ = rays;
        skip_ = skip;
        occluded_ = 0;
        if (tree.nodes.empty()) return false;
        alignas(32) float d[3][N], o[3][N], t0[N], t1[N];
        std::uint32_t negative[3] = {0, 0, 0};
        for (int i = 0; i < N; ++i) {
            const Ray& r = rays[i];
            t0[i] = r.tmin;
            t1[i] = r.tmax;
            for (int a = 0; a < 3; ++a) {
                d[a][i] = r.dir[a];
                o[a][i] = r.org[a];
                negative[a] |= (std::signbit(r.dir[a]) ? 1u : 0u) << i;
            }
        }
        std::uint32_t clipped = 0;
        for (int v = 0; v < K; ++v) {
            vf ov[3], dv[3];
            load_ray_vectors(o, d, v, ov, dv, org_, inv_);
            for (int a = 0; a < 3; ++a) dir_neg_[a][v] = vm::from_bits(negative[a] >> (W * v));
            vf lo = vf::load(t0 + W * v), hi = vf::load(t1 + W * v);
            const std::uint32_t lanes = mask >> (W * v) & ((1u << W) - 1u);
            const vm in = clip_rays_to_box<W>(tree.bounds, ov, dv, lo, hi, vm::from_bits(lanes));
            clipped |= static_cast<std::uint32_t>(in.bits()) << (W * v);
            tmin_[v] = lo;
            tmax_[v] = hi;
            ray_tmax_[v] = vf::load(t1 + W * v);
            live_[v] = in;
        }
        if (!clipped) return false;
        for (int i = 0; i < N; ++i) sheared_[i] = ShearedRay(rays[i].dir);
        for (int v = 0; v < K; ++v) sheared_v_[v] = ShearedRayV<W>(rays + W * v, sheared_ + W * v);
        top_ = 0;
        index_ = 0;
        leaf_stage_ = LeafStage::None;
        return true;
    }

    // The rays of the mask found blocked (final once run() returned true).
    std::uint32_t occluded() const { return occluded_; }

    bool run(const KdTree& tree, const Vec3f* tri_vertices, std::uint64_t& node_visits,
             std::uint64_t& triangle_tests) {
        constexpr float kInf = std::numeric_limits<float>::infinity();
        const Ray* rays = rays_;
        const vf zero = vf::broadcast(0.0f), v_inf = vf::broadcast(kInf), v_neg_inf = vf::broadcast(-kInf);
        const KdNode* nodes = tree.nodes.data();
        vf tmin[K], tmax[K];
        for (int v = 0; v < K; ++v) {
            tmin[v] = tmin_[v];
            tmax[v] = tmax_[v];
        }
        std::uint32_t index = index_;
        int top = top_;
        LeafStage leaf_stage = leaf_stage_;
        auto pause = [&](LeafStage next) {
            for (int v = 0; v < K; ++v) {
                tmin_[v] = tmin[v];
                tmax_[v] = tmax[v];
            }
            index_ = index;
            top_ = top;
            leaf_stage_ = next;
            return false;
        };
        for (;;) {
            const KdNode* node = nodes + index;
            vm active[K];
            bool leaf = true;
            if (leaf_stage == LeafStage::None) {
                for (;;) {
                    int any = 0;
                    for (int v = 0; v < K; ++v) {
                        active[v] = live_[v] & (tmin[v] <= tmax[v]);
                        any |= active[v].bits();
                    }
                    if (!any) {
                        leaf = false;
                        break;
                    }
                    if (node->is_leaf()) break;
                    ++node_visits;
                    const int axis = node->axis();
                    const float split = node->split();
                    const std::uint32_t left = node->left_empty() ? 0u : index + 1;
                    const std::uint32_t right = node->right_empty() ? 0u : index + node->right_offset();
                    // The packet's order: lane 0's own (its origin's side first).
                    const float o0 = rays[0].org[axis];
                    const bool near_is_left = o0 < split || (o0 == split && std::signbit(rays[0].dir[axis]));
                    const std::uint32_t near_child = near_is_left ? left : right;
                    const std::uint32_t far_child = near_is_left ? right : left;
                    PacketSplit<W, K> seg(split, near_is_left, true, org_[axis], inv_[axis], dir_neg_[axis], tmin,
                                          tmax, active);
                    int any_near = seg.any_near, any_far = seg.any_far;
                    if (near_child == 0) any_near = 0;
                    if (far_child == 0) any_far = 0;
                    if (!any_near && !any_far) {
                        leaf = false;
                        break;
                    }
                    if (any_near && any_far && top < kStack) {
                        Entry& e = stack_[top++];
                        e.node = far_child;
                        for (int v = 0; v < K; ++v) {
                            e.tmin[v] = select(seg.far_in[v], seg.far_lo[v], v_inf);
                            e.tmax[v] = select(seg.far_in[v], seg.far_hi[v], v_neg_inf);
                        }
                        if constexpr (Yield) prefetch_line(nodes + far_child);
                    }
                    const vf* lo_v = any_near ? seg.near_lo : seg.far_lo;
                    const vf* hi_v = any_near ? seg.near_hi : seg.far_hi;
                    const vm* in_v = any_near ? seg.near_in : seg.far_in;
                    for (int v = 0; v < K; ++v) {
                        tmin[v] = select(in_v[v], lo_v[v], v_inf);
                        tmax[v] = select(in_v[v], hi_v[v], v_neg_inf);
                    }
                    const std::uint32_t from = index;
                    index = any_near ? near_child : far_child;
                    node = nodes + index;
                    if constexpr (Yield) {
                        if (!near_in_memory(nodes + from, node)) {
                            prefetch_line(node);
                            return pause(LeafStage::None);
                        }
                    }
                }
                if (leaf) {
                    if constexpr (Yield) {
                        prefetch_line(tree.tri_ids.data() + node->first());
                        return pause(LeafStage::Ids);
                    }
                }
            } else {
                if (leaf_stage == LeafStage::Ids) {
                    // The ids are in; ask for the first triangles' vertices and wait again.
                    prefetch_leaf_vertices(tree, tri_vertices, *node);
                    return pause(LeafStage::Vertices);
                }
                for (int v = 0; v < K; ++v) active[v] = live_[v] & (tmin[v] <= tmax[v]);
                leaf_stage = LeafStage::None;
            }
            if (leaf) {
                const std::uint32_t count = node->count();
                const std::uint32_t* ids = tree.tri_ids.data() + node->first();
                int act[K];
                for (int v = 0; v < K; ++v) act[v] = active[v].bits();
                for (std::uint32_t t = 0; t < count; ++t) {
                    const std::uint32_t id = ids[t];
                    const Vec3f* p = tri_vertices + 3 * static_cast<std::size_t>(id);
                    for (int v = 0; v < K; ++v) {
                        int lanes = act[v];
                        if (skip_ && lanes) {
                            for (int k = 0; k < W; ++k) lanes &= ~((skip_[W * v + k] == id ? 1 : 0) << k);
                        }
                        if (!lanes) continue;
                        triangle_tests += static_cast<std::uint64_t>(__builtin_popcount(static_cast<unsigned>(lanes)));
                        // No hit yet (a lane retires at its first): test against [tmin, tmax).
                        HitV<W> hv{ray_tmax_[v], zero, zero, vf::bits(kNoHit)};
                        const int changed = intersect_triangle_v<W>(sheared_v_[v], rays + W * v, sheared_ + W * v,
                                                                    p[0], p[1], p[2], id,
                                                                    vm::from_bits(static_cast<unsigned>(lanes)), hv);
                        occluded_ |= static_cast<std::uint32_t>(changed) << (W * v);
                        act[v] &= ~changed;
                        live_[v] = andnot(vm::from_bits(static_cast<unsigned>(changed)), live_[v]);
                    }
                    int any = 0;
                    for (int v = 0; v < K; ++v) any |= act[v];
                    if (!any) break;
                }
            }
            for (;;) {
                int live_bits = 0;
                for (int v = 0; v < K; ++v) live_bits |= live_[v].bits();
                if (top == 0 || !live_bits) return true;
                const Entry& e = stack_[--top];
                int any = 0;
                for (int v = 0; v < K; ++v) {
                    const vm in = live_[v] & (e.tmin[v] <= e.tmax[v]);
                    tmin[v] = select(in, e.tmin[v], v_inf);
                    tmax[v] = select(in, e.tmax[v], v_neg_inf);
                    any |= in.bits();
                }
                if (!any) continue;
                index = e.node;
                break;
            }
        }
    }

private:
    struct Entry {
        vf tmin[K], tmax[K];
        std::uint32_t node;
    };
    static constexpr int kStack = 64;

    const Ray* rays_ = nullptr;
    const std::uint32_t* skip_ = nullptr;
    ShearedRay sheared_[N];
    ShearedRayV<W> sheared_v_[K];
    vf inv_[3][K], org_[3][K], tmin_[K], tmax_[K], ray_tmax_[K];
    vm live_[K], dir_neg_[3][K];
    std::uint32_t occluded_ = 0;
    std::uint32_t index_ = 0;
    int top_ = 0;
    enum class LeafStage : std::uint8_t { None, Ids, Vertices };  // what a paused walk waits for
    LeafStage leaf_stage_ = LeafStage::None;
    Entry stack_[kStack];
};

}  // namespace kd_detail

// Any-hit queries of N rays in lane order (shadow and AO rays): returns the rays of
// `mask` that hit a triangle in [tmin, tmax) other than skip[i]. Each lane walks exactly
// the single ray's segments (PacketSplit: the child on its origin's side first, as
// traverse() does), and as the answer does not depend on the order of the walk, any
// rays may share a packet, which takes the children in lane 0's order. Packets pay where
// the rays' paths agree: a shared origin (the AO rays of a point) or a shared direction
// (the shadow rays of a pixel block). (They do not hand a lone ray to a single walk,
// as the out-of-core AO packets do: in core the packet step is cheap, and the hand-over
// cost the AO query 0.82x, docs/native-core.md.)
template <int N>
inline std::uint32_t occluded_packet(const KdTree& tree, const Vec3f* tri_vertices, const Ray* rays,
                                     const std::uint32_t* skip, std::uint32_t mask, TraversalCounters& counters) {
    kd_detail::OcclusionWalker<N, false> walker;
    if (!walker.start(tree, rays, skip, mask)) return 0;
    std::uint64_t node_visits = 0, triangle_tests = 0;
    walker.run(tree, tri_vertices, node_visits, triangle_tests);
    counters.node_visits += node_visits;
    counters.triangle_tests += triangle_tests;
    return walker.occluded();
}

// occluded_packet of `count` packets at once (rays[j], skip[j] or null, mask[j]),
// G of them in flight; blocked[j] gets packet j's answer.
template <int N, int G>
inline void occluded_packets(const KdTree& tree, const Vec3f* tri_vertices, const Ray* const* rays,
                             const std::uint32_t* const* skip, const std::uint32_t* mask, std::uint32_t* blocked,
                             int count, TraversalCounters& counters) {
    kd_detail::OcclusionWalker<N, true> walkers[G];
    int of[G];
    std::uint64_t node_visits = 0, triangle_tests = 0;
    int next = 0;
    walks_in_flight<G>(
        [&](int g) {
            while (next < count) {
                const int j = next++;
                blocked[j] = 0;
                if (walkers[g].start(tree, rays[j], skip ? skip[j] : nullptr, mask[j])) {
                    of[g] = j;
                    return true;
                }
            }
            return false;
        },
        [&](int g) {
            if (!walkers[g].run(tree, tri_vertices, node_visits, triangle_tests)) return false;
            blocked[of[g]] = walkers[g].occluded();
            return true;
        });
    counters.node_visits += node_visits;
    counters.triangle_tests += triangle_tests;
}

VASTRAY_KERNEL_END
