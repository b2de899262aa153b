// Coherent primary packets through the 8-wide BVH (wide_bvh.h): the N rays of a pixel
// block, whose direction signs agree, walk the tree together. A node is loaded once for
// the packet; interval bounds over the packet rule out the children no ray can enter,
// and each remaining box is tested against every active ray with that ray's own slab
// arithmetic (WideBoxTest's, lane by lane): a ray enters a box only where it meets the
// box before its hit so far, as in its single walk. A child entered by one ray only is
// left to that ray's single walk (closest_wide's), which is what the wide node is best
// at. Leaves test each active ray with the single ray's quad test. The hit of every ray
// is closest_wide's bit for bit: the leaves decide by a strict order on (t, index)
// (quad_closest), so the order in which the packet meets the triangles does not matter.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

#include "vastray/isa.h"
#include "vastray/packet.h"
#include "vastray/simd.h"
#include "vastray/wide_traverse.h"

VASTRAY_KERNEL_BEGIN

namespace wide_detail {

#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
template <int N>
class WidePacket {
    static constexpr int W = packet_width<N>();
    static constexpr int K = N / W;
    static constexpr int C = WideNode::kWidth;
    static constexpr float kInf = std::numeric_limits<float>::infinity();
    using vf = simd::vfloat<W>;
    using vm = simd::vmask<W>;

public:
    // Rays and hits in lane order (they stay in place until step() returns true); every
    // direction component non-zero, with the same sign across the packet.
    void start(const Ray* rays_in, Hit* hits_out) {
        rays = rays_in;
        hits = hits_out;
        alignas(64) float o[3][N], i_near[3][N], i_far[3][N], t0[N];
        for (int i = 0; i < N; ++i) {
            hits[i].t = rays[i].tmax;
            hits[i].prim = kNoHit;
            hit_t[i] = rays[i].tmax;
            t0[i] = rays[i].tmin;
            for (int a = 0; a < 3; ++a) {
                const float inv = 1.0f / rays[i].dir[a];
                o[a][i] = rays[i].org[a];
                i_near[a][i] = inv * (1.0f - kSplitSlack);
                i_far[a][i] = inv * (1.0f + kSplitSlack);
            }
        }
        for (int v = 0; v < K; ++v) {
            for (int a = 0; a < 3; ++a) {
                org[a][v] = vf::load(o[a] + W * v);
                inv_near[a][v] = vf::load(i_near[a] + W * v);
                inv_far[a][v] = vf::load(i_far[a] + W * v);
            }
            tmin[v] = vf::load(t0 + W * v);
        }
        for (int a = 0; a < 3; ++a) {
            const int lo = 2 * C * a, hi = lo + C;
            near_row[a] = std::signbit(rays[0].dir[a]) ? hi : lo;
            far_row[a] = std::signbit(rays[0].dir[a]) ? lo : hi;
            o_lo[a] = o_hi[a] = o[a][0];
            in_lo[a] = in_hi[a] = i_near[a][0];
            if_lo[a] = if_hi[a] = i_far[a][0];
            for (int i = 1; i < N; ++i) {
                o_lo[a] = std::min(o_lo[a], o[a][i]);
                o_hi[a] = std::max(o_hi[a], o[a][i]);
                in_lo[a] = std::min(in_lo[a], i_near[a][i]);
                in_hi[a] = std::max(in_hi[a], i_near[a][i]);
                if_lo[a] = std::min(if_lo[a], i_far[a][i]);
                if_hi[a] = std::max(if_hi[a], i_far[a][i]);
            }
        }
        t0_lo = t0[0];
        for (int i = 1; i < N; ++i) t0_lo = std::min(t0_lo, t0[i]);
        quad_set = 0;
        lanes = N == 32 ? ~0u : (1u << N) - 1;
        cur = 0;
        top = 0;
        lone = -1;
    }

    // Visits the next node or leaf (of the packet, or of the ray walking alone); true
    // when the walk is over. Otherwise the next one's lines have been asked for.
    bool step(const WideBvh& bvh, std::uint64_t& node_visits, std::uint64_t& triangle_tests) {
        if (lone >= 0) {
            if (!lone_step(bvh, node_visits, triangle_tests)) return false;
        } else if (WideNode::is_leaf(cur)) {
            leaf(bvh, triangle_tests);
        } else if ((lanes & (lanes - 1)) == 0) {
            // One ray left in this subtree: its own walk takes it, as closest_wide would
            // (handing over two or three as well measured the same).
            lone = __builtin_ctz(lanes);
            lone_walk.resume(rays[lone], hits[lone], cur);
            if (!lone_step(bvh, node_visits, triangle_tests)) return false;
        } else {
            ++node_visits;
            if (descend(bvh.nodes[cur])) {
                WideWalkRay::prefetch(bvh, cur);
                return false;
            }
        }
        // The next entry some of whose rays may still find a nearer hit there.
        for (;;) {
            if (top == 0) return true;
            const Entry& e = stack[--top];
            lanes = e.lanes & nearer_than(e.t);
            if (lanes) {
                cur = e.code;
                WideWalkRay::prefetch(bvh, cur);
                return false;
            }
        }
    }

private:
    struct Entry {
        std::uint32_t code, lanes;
        float t;  // the nearest entry distance of its rays
    };

    // One step of the lone ray's walk (closest_wide's); true when it is over.
    bool lone_step(const WideBvh& bvh, std::uint64_t& node_visits, std::uint64_t& triangle_tests) {
        if (!lone_walk.step(bvh, node_visits, triangle_tests)) return false;
        hit_t[lone] = hits[lone].t;
        lone = -1;
        return true;
    }

    void shear(int i) {
        if (quad_set >> i & 1u) return;
        sheared[i] = ShearedRay(rays[i].dir);
        quad_ray[i] = QuadRay(rays[i], sheared[i]);
        quad_set |= 1u << i;
    }

    // The rays whose closest hit so far lies at or beyond t.
    std::uint32_t nearer_than(float t) const {
        const vf tv = vf::broadcast(t);
        std::uint32_t bits = 0;
        for (int v = 0; v < K; ++v) {
            bits |= static_cast<std::uint32_t>((tv <= vf::load(hit_t + W * v)).bits()) << (W * v);
        }
        return bits;
    }

    // The node's children entered by some of `lanes`: the nearest becomes `cur` with its
    // rays, the others go on the stack, farthest first. The children no ray of the packet
    // can enter are found first, for all eight at once: each ray's entry and exit
    // distances lie within the bounds that interval arithmetic gives over the packet's
    // origins and 1/d (rounding is monotone, so the bounds hold for the rounded distances
    // too), and a child is entered only by the rays that WideBoxTest::hits would send
    // there. "Nearest" is by those bounds on entry, which also stand for the child's
    // entry on the stack (no ray of it enters before). False: no child is entered.
    bool descend(const WideNode& node) {
        using bf = simd::vfloat<kBoxLanes>;
        const float* base = node.lo_x;
        vf tmax[K];
        vm active[K];
        vf far_end = vf::broadcast(-kInf);
        for (int v = 0; v < K; ++v) {
            tmax[v] = vf::load(hit_t + W * v);
            active[v] = vm::from_bits(lanes >> (W * v));
            far_end = max(select(active[v], tmax[v], vf::broadcast(-kInf)), far_end);
        }
        alignas(64) float ends[W];
        far_end.store(ends);
        float packet_end = ends[0];
        for (int k = 1; k < W; ++k) packet_end = std::max(packet_end, ends[k]);
        alignas(64) float entry_lo[C];
        unsigned candidates = 0;
        for (int h = 0; h < C / kBoxLanes; ++h) {
            const int off = h * kBoxLanes;
            bf tn = bf::broadcast(t0_lo), tf = bf::broadcast(packet_end);
            for (int a = 0; a < 3; ++a) {
                const bf olo = bf::broadcast(o_lo[a]), ohi = bf::broadcast(o_hi[a]);
                const bf p = bf::load(base + near_row[a] + off);
                const bf dlo = p - ohi, dhi = p - olo;
                const bf ilo = bf::broadcast(in_lo[a]), ihi = bf::broadcast(in_hi[a]);
                tn = max(min(min(dlo * ilo, dlo * ihi), min(dhi * ilo, dhi * ihi)), tn);
                const bf q = bf::load(base + far_row[a] + off);
                const bf qlo = q - ohi, qhi = q - olo;
                const bf jlo = bf::broadcast(if_lo[a]), jhi = bf::broadcast(if_hi[a]);
                tf = min(max(max(qlo * jlo, qlo * jhi), max(qhi * jlo, qhi * jhi)), tf);
            }
            tn.store(entry_lo + off);
            candidates |= static_cast<unsigned>((tn <= tf).bits()) << off;
        }
        std::uint32_t child_lanes[C];
        int order[C], n = 0;
        for (; candidates != 0; candidates &= candidates - 1) {
            const int c = __builtin_ctz(candidates);
            const vf px = vf::broadcast(base[near_row[0] + c]), py = vf::broadcast(base[near_row[1] + c]),
                     pz = vf::broadcast(base[near_row[2] + c]);
            const vf qx = vf::broadcast(base[far_row[0] + c]), qy = vf::broadcast(base[far_row[1] + c]),
                     qz = vf::broadcast(base[far_row[2] + c]);
            std::uint32_t bits = 0;
            for (int v = 0; v < K; ++v) {
                // WideBoxTest::hits, lane by lane: the same operations in the same order.
                const vf nx = (px - org[0][v]) * inv_near[0][v];
                const vf ny = (py - org[1][v]) * inv_near[1][v];
                const vf nz = (pz - org[2][v]) * inv_near[2][v];
                const vf fx = (qx - org[0][v]) * inv_far[0][v];
                const vf fy = (qy - org[1][v]) * inv_far[1][v];
                const vf fz = (qz - org[2][v]) * inv_far[2][v];
                const vf tnv = max(nx, max(ny, max(nz, tmin[v])));
                const vf tfv = min(fx, min(fy, min(fz, tmax[v])));
                bits |= static_cast<std::uint32_t>((active[v] & (tnv <= tfv)).bits()) << (W * v);
            }
            if (!bits) continue;
            child_lanes[c] = bits;
            const float t = entry_lo[c];
            int j = n++;
            for (; j > 0 && entry_lo[order[j - 1]] < t; --j) order[j] = order[j - 1];
            order[j] = c;
        }
        if (n == 0) return false;
        for (int j = 0; j < n - 1; ++j) {
            stack[top++] = {node.child[order[j]], child_lanes[order[j]], entry_lo[order[j]]};
        }
        cur = node.child[order[n - 1]];
        lanes = child_lanes[order[n - 1]];
        return true;
    }

    void leaf(const WideBvh& bvh, std::uint64_t& triangle_tests) {
        for (std::uint32_t l = lanes; l != 0; l &= l - 1) {
            const int i = __builtin_ctz(l);
            shear(i);
            wide_leaf_nearest(bvh, cur, quad_ray[i], rays[i], sheared[i], kNoHit, hits[i], triangle_tests);
            hit_t[i] = hits[i].t;
        }
    }

    const Ray* rays = nullptr;
    Hit* hits = nullptr;
    vf org[3][K], inv_near[3][K], inv_far[3][K], tmin[K];
    int near_row[3], far_row[3];
    // The packet's bounds: origins, 1/d scaled for entries and exits, and tmin.
    float o_lo[3], o_hi[3], in_lo[3], in_hi[3], if_lo[3], if_hi[3], t0_lo;
    alignas(64) float hit_t[N];
    std::uint32_t quad_set = 0, lanes = 0, cur = 0;
    int top = 0;
    ShearedRay sheared[N];
    QuadRay quad_ray[N];
    Entry stack[kWideStack];
    int lone = -1;  // the ray walking alone below `cur`, or -1
    WideClosestWalk lone_walk;
};
#pragma GCC diagnostic pop

}  // namespace wide_detail

// Closest hits of `count` packets of N coherent rays in row order (packet_is_coherent)
// through the wide BVH, G in flight (walks_in_flight; G = 1: one after the other):
// hits[j][i] is ray i of packet j's, closest_wide's.
template <int N, int G>
inline void closest_wide_packets(const WideBvh& bvh, const Ray* const* rays, Hit* const* hits, int count,
                                 TraversalCounters& counters) {
    constexpr int W = packet_width<N>();
    struct Slot {
        Ray rays[N];
        Hit hits[N];
        int j = -1;
        wide_detail::WidePacket<N> walk;
    };
    Slot slots[G];
    int next = 0;
    std::uint64_t node_visits = 0, triangle_tests = 0;
    const auto finish = [&](Slot& s) {
        for (int i = 0; i < N; ++i) hits[s.j][i] = s.hits[packet_lane<N, W>(i)];
    };
    walks_in_flight<G>(
        [&](int g) {
            if (next >= count) return false;
            Slot& s = slots[g];
            s.j = next++;
            for (int i = 0; i < N; ++i) s.rays[packet_lane<N, W>(i)] = rays[s.j][i];
            s.walk.start(s.rays, s.hits);
            return true;
        },
        [&](int g) {
            if (!slots[g].walk.step(bvh, node_visits, triangle_tests)) return false;
            finish(slots[g]);
            return true;
        });
    counters.node_visits += node_visits;
    counters.triangle_tests += triangle_tests;
}

VASTRAY_KERNEL_END
