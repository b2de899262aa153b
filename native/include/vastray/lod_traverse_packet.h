// Packet versions of lod_traverse: N rays walk the cached tree together, in N / W SIMD
// vectors (packet.h). One node fetch, one block lookup and one decision serve the
// packet; each ray keeps its own segment, LOD test, voxel hit and termination, computed
// lane by lane with exactly the single-ray arithmetic, so a packet changes speed, never
// answers (tests compare full-detail frames bit for bit).
//
// Two kinds of packet (LodPacketOrder):
//   SharedOrigin  rays from one point: the primary rays of a pixel block (closest hit,
//                 and every direction sign alike), or the AO rays of one pixel (any hit,
//                 any directions). The packet visits the child on the origin's side of
//                 each plane first, which is every ray's own near child.
//   SharedSigns   rays whose directions agree in sign on every axis, from any origins:
//                 the shadow rays of a pixel block towards the sun (any hit). The packet
//                 visits the child the directions point away from first; a ray whose
//                 origin lies beyond the plane has only that one child to visit anyway.
// Either way a lane's segments in the two children are the single-ray ones, mapped to
// the packet's order. Any-hit packets retire a ray at its first triangle or voxel; their
// answers do not depend on the order at all.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>

#include "vastray/isa.h"
#include "vastray/prefetch.h"
#include "vastray/lod_traverse.h"
#include "vastray/packet.h"

VASTRAY_KERNEL_BEGIN

enum class LodPacketOrder { SharedOrigin, SharedSigns };

// Primary packets: a shared origin and cone, every direction component non-zero with
// the same sign across the packet. (Tested for every 4x4 block of a frame: one pass
// over the rays, without a branch per component.)
template <int N>
inline bool lod_packet_is_coherent(const LodRay* rays) {
    const Ray& first = rays[0].ray;
    std::uint32_t sign[3], zero = 0, differ = 0;
    for (int a = 0; a < 3; ++a) sign[a] = format::float_bits(first.dir[a]) >> 31;
    for (int k = 0; k < N; ++k) {
        const Ray& r = rays[k].ray;
        for (int a = 0; a < 3; ++a) {
            zero |= r.dir[a] == 0.0f ? 1u : 0u;
            differ |= (format::float_bits(r.dir[a]) >> 31) ^ sign[a];
            differ |= r.org[a] != first.org[a] ? 1u : 0u;
        }
    }
    return (zero | differ) == 0 && rays[0].cone == rays[N - 1].cone && rays[0].cone_t0 == rays[N - 1].cone_t0;
}

namespace lod_detail {

// Lanes k of `ids` equal to `id`, as bits.
template <int W>
inline int equal_lanes(const std::uint32_t* ids, std::uint32_t id) {
    int m = 0;
    for (int k = 0; k < W; ++k) m |= (ids[k] == id ? 1 : 0) << k;
    return m;
}

}  // namespace lod_detail

namespace lod_detail {

// The walk of one packet (lod_packet_walk) as an object, for a full-precision
// (Quantized = false) or quantized model. With Yield = false, run() goes to the end of
// the walk. With Yield = true it also stops where the packet is about to wait for
// memory, having asked for it: on entering a child treelet (the lines of the pair) and
// on reaching a leaf (LeafPrefetch's waits). A caller with several packets in flight
// (lod_trace_packets) runs the others meanwhile, so that their misses overlap. Either
// way every ray does the same arithmetic in the same order.
//
// GCC cannot see that an entry is popped only after it was pushed (top counts them),
// and calls the stack maybe-uninitialised; it is left uninitialised on purpose (a
// packet walk starts for every 16 rays, and clearing 64 entries would cost more).
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
template <int N, bool AnyHit, LodPacketOrder Order, bool Quantized, bool Yield>
class PacketWalker {
    static_assert(N <= 32, "ray masks are 32-bit");
    static constexpr int W = packet_width<N>();
    static constexpr int K = N / W;
    static constexpr bool kShared = Order == LodPacketOrder::SharedOrigin;
    static constexpr float kInf = std::numeric_limits<float>::infinity();
    using vf = simd::vfloat<W>;
    using vm = simd::vmask<W>;

public:
    // Sets up the packet: rays, hits and skips in lane order, which must stay in place
    // until run() returns true; `mask` selects the rays to trace. False when no ray
    // enters the model (the hits are then already written).
    bool start(LodLane& lane, const Box3f& root_cell, const LodRay* rays_in, LodHit* hits_out,
               const std::uint32_t* skip_in, std::uint32_t mask) {
        rays = rays_in;
        hits = hits_out;
        skip = skip_in;
        occluded = 0;
        alignas(32) float d[3][N], o[3][N], t0[N], ray_t0[N], ray_t1[N];
        std::uint32_t negative[3] = {0, 0, 0};
        for (int i = 0; i < N; ++i) {
            const Ray& r = rays[i].ray;
            hits[i].t = r.tmax;
            hits[i].prim = kNoHit;
            for (int a = 0; a < 3; ++a) {
                d[a][i] = r.dir[a];
                o[a][i] = r.org[a];
                negative[a] |= (std::signbit(r.dir[a]) ? 1u : 0u) << i;
            }
            t0[i] = rays[i].cone_t0;
            ray_t0[i] = r.tmin;
            ray_t1[i] = r.tmax;
        }
        std::uint32_t clipped = 0;
        for (int v = 0; v < K; ++v) {
            const std::uint32_t lanes = mask >> (W * v) & ((W == 32 ? 0u : 1u << W) - 1u);
            clipped |= static_cast<std::uint32_t>(clip_root(root_cell, o, d, ray_t0, ray_t1, v, lanes)) << (W * v);
        }
        if (!clipped) return false;
        const std::uint8_t* root = lane.lookup(lane.level_first[0], 0.0f);
        if (!root) return false;

        for (int i = 0; i < N; ++i) sheared[i] = ShearedRay(rays[i].ray.dir);
        for (int v = 0; v < K; ++v) {
            sheared_v[v] = ShearedRayV<W>(rays + W * v, sheared + W * v);
            for (int a = 0; a < 3; ++a) {
                const vf dv = vf::load(d[a] + W * v);
                inv[a][v] = vf::broadcast(1.0f) / dv;
                org[a][v] = vf::load(o[a] + W * v);
                dir_neg[a][v] = vm::from_bits(negative[a] >> (W * v));
            }
            cone_t0[v] = vf::load(t0 + W * v);
            hit_t[v] = HitV<W>::load(hits + W * v).t;
            live[v] = vm::from_bits(clipped >> (W * v));
        }
        for (int a = 0; a < 3; ++a) sign_negative[a] = std::signbit(rays[0].ray.dir[a]);
        // Rays of mixed direction signs (the AO rays of a point) part early and walk most
        // of the tree alone: there the single-ray walk takes a ray left alone. Coherent
        // packets keep theirs (see walk_lone).
        lone_walks = false;
        for (int a = 0; a < 3; ++a) {
            const std::uint32_t neg = negative[a] & mask;
            lone_walks = lone_walks || (neg != 0 && neg != mask);
        }
        top = 0;
        node = lod_detail::root_ref(root, root_cell);
        voxel = Voxel{nullptr, 0.0f, 0.0f};
        stage = Stage::Descend;
        leaf_.stage = 0;
        return true;
    }

    // Walks on; true when the walk is over (closest hit: hits written; any hit:
    // occluded_rays() is the answer).
    bool run(LodLane& lane) {
        using namespace format;
        using lod_detail::load;
        const float cone = rays[0].cone;
        const vf v_cone = vf::broadcast(cone);
        const vf v_inf = vf::broadcast(kInf), v_neg_inf = vf::broadcast(-kInf);

        // The lanes `which` of vector v stop at voxel `vx`, entered at their current tmin.
        auto take_voxels = [&](const Voxel& vx, int v, int which) {
            if (AnyHit) {
                // A voxel counts where it lies before the ray's end, as in lod_traverse().
                const int before = (tmin[v] < hit_t[v]).bits() & which;
                occluded |= static_cast<std::uint32_t>(before) << (W * v);
                lane.voxel_hits += static_cast<std::uint64_t>(__builtin_popcount(static_cast<unsigned>(which)));
            } else {
                alignas(32) float tv[W], ax[W];
                tmin[v].store(tv);
                axis_in[v].store(ax);
                for (int k = 0; k < W; ++k) {
                    if (!(which >> k & 1)) continue;
                    LodHit& h = hits[W * v + k];
                    if (tv[k] < h.t) lod_detail::hit_voxel(vx, static_cast<int>(ax[k]), rays[W * v + k].ray, tv[k], h);
                    ++lane.voxel_hits;
                }
                hit_t[v] = HitV<W>::load(hits + W * v).t;
            }
            live[v] = andnot(vm::from_bits(static_cast<unsigned>(which)), live[v]);
        };
        auto nearest_of = [&](const vm* act) {
            vf nearest = v_inf;
            for (int v = 0; v < K; ++v) nearest = min(select(act[v], tmin[v] + cone_t0[v], v_inf), nearest);
            alignas(32) float near_t[W];
            nearest.store(near_t);
            float reach = kInf;
            for (int k = 0; k < W; ++k) reach = std::min(reach, near_t[k]);
            return reach;
        };

        for (;;) {
            bool leaf = false;
            vm active[K];
            if (Yield && stage == Stage::Leaf) {
                // Back at the leaf it stopped at: the next wait, or its triangles.
                if (leaf_.waiting()) {
                    leaf_.next(lane, node.block + node.off);
                    return false;
                }
                leaf_.stage = 0;
                stage = Stage::Descend;
                leaf = true;
                for (int v = 0; v < K; ++v) active[v] = live[v] & (tmin[v] <= tmax[v]);
            }
            while (!leaf) {
                std::uint32_t lanes = 0;
                for (int v = 0; v < K; ++v) {
                    active[v] = live[v] & (tmin[v] <= tmax[v]);
                    lanes |= static_cast<std::uint32_t>(active[v].bits()) << (W * v);
                }
                if (!lanes) break;
                if (lone_walks && (lanes & (lanes - 1)) == 0) {
                    walk_lone(lane, __builtin_ctz(lanes));
                    break;
                }
                const std::uint32_t w = load<std::uint32_t>(node.block + node.off);
                if (!is_inner(w)) {
                    leaf = true;
                    if constexpr (Yield) {
                        if (leaf_.start(lane, node.block + node.off)) {
                            stage = Stage::Leaf;
                            return false;
                        }
                    }
                    break;
                }
                ++lane.node_visits;
                const int axis = std::min(axis_of(w), 2);
                const float split = lod_detail::split_of(Quantized, lane.voxel_errors, node, w);
                const std::uint8_t* child_block = node.block;
                std::uint32_t child_level = node.level;
                if (is_lod(w)) {
                    const Voxel here = lod_detail::voxel_of(Quantized, lane.packed_treelets, lane.voxel_errors, node, w);
                    const vf error = vf::broadcast(here.error);
                    int rest = 0;
                    for (int v = 0; v < K; ++v) {
                        const vm accept = active[v] & (error <= (cone_t0[v] + tmin[v]) * v_cone);
                        if (const int a = accept.bits(); a != 0) take_voxels(here, v, a);
                        active[v] = andnot(accept, active[v]);
                        rest |= active[v].bits();
                    }
                    if (!rest) break;
                    child_block = lod_detail::lod_child_block(
                        lane, node, [&] { return here.error / std::max(nearest_of(active), 1e-30f); });
                    if (!child_block) {
                        for (int v = 0; v < K; ++v) {
                            if (const int a = active[v].bits(); a != 0) take_voxels(here, v, a);
                        }
                        break;
                    }
                    voxel = here;
                    child_level = node.level + 1;
                }
                // The children's offsets (no NodeRef copies: only the child the packet enters
                // and the one it puts aside are written).
                const bool has_l = (w & kLeftEmpty) == 0, has_r = (w & kRightEmpty) == 0;
                std::uint32_t l_off, r_off;
                if (!lod_detail::child_offsets<Quantized>(w, node.off, lane.packed_treelets, l_off, r_off)) {
                    return true;  // damaged
                }
                // The packet's near child: the origin's side (shared origin), else the side
                // the directions leave.
                bool near_is_left, may_flip = true;
                if constexpr (kShared) {
                    const float o0 = rays[0].ray.org[axis];
                    near_is_left = o0 < split || (o0 == split && sign_negative[axis]);
                    may_flip = o0 == split;  // else the origin's side is every ray's near side
                } else {
                    near_is_left = !sign_negative[axis];
                }
                const bool has_near = near_is_left ? has_l : has_r, has_far = near_is_left ? has_r : has_l;
                const std::uint32_t near_off = near_is_left ? l_off : r_off, far_off = near_is_left ? r_off : l_off;
                // Moves `to` (a copy of the node) to one of its children: the left one keeps the
                // cell's low side, the right one its high side (quantized models only).
                auto enter = [&](NodeRef& to, bool left, std::uint32_t child_off) {
                    to.block = child_block;
                    to.off = child_off;
                    to.level = child_level;
                    if constexpr (Quantized) {
                        if (left) to.hi[axis] = split;
                        else to.lo[axis] = split;
                    }
                };
                PacketSplit<W, K> seg(split, near_is_left, may_flip, org[axis], inv[axis], dir_neg[axis], tmin, tmax,
                                      active);
                int any_near = has_near ? seg.any_near : 0, any_far = has_far ? seg.any_far : 0;
                const vf axis_v = vf::broadcast(static_cast<float>(axis));
                if (any_near && any_far && top < 64) {
                    // The far child is needed later: start its load now, beside the near one's.
                    prefetch_line(child_block + far_off);
                    Entry& e = stack[top++];
                    if constexpr (Quantized) e.node = node;  // (its cell; the rest is set below)
                    enter(e.node, !near_is_left, far_off);
                    e.voxel = voxel;
                    // Segments go in as they are, without clearing the lanes outside the
                    // child: a lane that is not active has an empty segment (tmin > tmax,
                    // or it is no longer live), the split keeps it empty in both children,
                    // and every use of a segment is masked by the active or live lanes.
                    for (int v = 0; v < K; ++v) {
                        e.tmin[v] = seg.far_lo[v];
                        e.tmax[v] = seg.far_hi[v];
                        e.axis[v] = select(seg.far_lo[v] > tmin[v], axis_v, axis_in[v]);
                    }
                }
                const vf* lo_v = any_near ? seg.near_lo : seg.far_lo;
                const vf* hi_v = any_near ? seg.near_hi : seg.far_hi;
                if (!any_near && !any_far) break;
                for (int v = 0; v < K; ++v) {
                    axis_in[v] = select(lo_v[v] > tmin[v], axis_v, axis_in[v]);
                    tmin[v] = lo_v[v];
                    tmax[v] = hi_v[v];
                }
                enter(node, any_near ? near_is_left : !near_is_left, any_near ? near_off : far_off);
                if constexpr (Yield) {
                    if (is_lod(w)) {
                        // Into a child treelet, in another block: ask for the lines of the
                        // pair (stored back to back) and let the other packets run.
                        const std::uint32_t first = std::min(l_off, r_off);
                        const std::size_t span =
                            std::min<std::size_t>(std::max(l_off, r_off) - first + 128, kBlockSize - first);
                        for (std::size_t b = 0; b < span; b += 64) prefetch_line(child_block + first + b);
                        return false;
                    }
                }
            }
            if (leaf) {
                const auto priority = [&] {
                    return voxel.samples ? voxel.error / std::max(nearest_of(active), 1e-30f) : 0.0f;
                };
                lod_detail::LeafTriangles triangles(lane, node.block + node.off, priority);
                HitV<W> hv[K];
                int act[K];
                for (int v = 0; v < K; ++v) {
                    hv[v] = HitV<W>::load(hits + W * v);
                    act[v] = active[v].bits();
                }
                Vec3f v0, v1, v2;
                std::uint32_t local;
                while (triangles.next(v0, v1, v2, local)) {
                    // The input id is read here only for a skip test. A hit records the
                    // triangle's index in its block as its prim (never kNoHit), and the
                    // id is read when the walk is over (resolve_triangle_ids).
                    std::uint32_t id = kNoHit;
                    for (int v = 0; v < K; ++v) {
                        int lanes = act[v];
                        if (skip && lanes) {
                            if (id == kNoHit) id = triangles.id(local);
                            lanes &= ~lod_detail::equal_lanes<W>(skip + W * v, id);
                        }
                        if (!lanes) continue;
                        lane.triangle_tests += static_cast<std::uint64_t>(__builtin_popcount(static_cast<unsigned>(lanes)));
                        const int changed = intersect_triangle_v<W>(sheared_v[v], rays + W * v, sheared + W * v, v0, v1,
                                                                    v2, local, vm::from_bits(static_cast<unsigned>(lanes)),
                                                                    hv[v]);
                        if (!AnyHit && changed) triangles.prefetch_hit(local);
                        if (AnyHit) {
                            // Retired at their first hit.
                            occluded |= static_cast<std::uint32_t>(changed) << (W * v);
                            act[v] &= ~changed;
                            live[v] = andnot(vm::from_bits(static_cast<unsigned>(changed)), live[v]);
                        } else {
                            for (int k = 0; k < W; ++k) {
                                if (!(changed >> k & 1)) continue;
                                hits[W * v + k].tri_block = triangles.block();
                                hits[W * v + k].local = local;
                            }
                        }
                    }
                    if constexpr (AnyHit) {
                        int any = 0;
                        for (int v = 0; v < K; ++v) any |= act[v];
                        if (!any) break;
                    }
                }
                const bool missing = triangles.missing();
                const vf end_scale = vf::broadcast(1.0f + kSplitSlack);
                for (int v = 0; v < K; ++v) {
                    if (!act[v]) continue;
                    if (!AnyHit) {
                        hv[v].store(hits + W * v);
                        hit_t[v] = hv[v].t;
                    }
                    if (missing) {
                        // Triangles not here yet: the last voxel passed stands in for them.
                        if (voxel.samples) take_voxels(voxel, v, act[v]);
                        continue;
                    }
                    if (AnyHit) continue;
                    // A lane with a hit of its own (this leaf's or an earlier one) that lies
                    // inside this cell is finished.
                    int has_hit = 0;
                    for (int k = 0; k < W; ++k) has_hit |= (hits[W * v + k].prim != kNoHit ? 1 : 0) << k;
                    const vm done = active[v] & vm::from_bits(static_cast<unsigned>(has_hit)) &
                                    (hv[v].t * end_scale < tmax[v]);
                    live[v] = andnot(done, live[v]);
                }
            }
            for (;;) {
                int live_bits = 0;
                for (int v = 0; v < K; ++v) live_bits |= live[v].bits();
                if (top == 0 || !live_bits) return true;
                const Entry& e = stack[--top];
                int any = 0;
                for (int v = 0; v < K; ++v) {
                    const vm in = live[v] & (e.tmin[v] <= e.tmax[v]) & andnot(e.tmin[v] > hit_t[v], live[v]);
                    tmin[v] = select(in, e.tmin[v], v_inf);
                    tmax[v] = select(in, e.tmax[v], v_neg_inf);
                    axis_in[v] = e.axis[v];
                    any |= in.bits();
                }
                if (!any) continue;
                node = e.node;
                voxel = e.voxel;
                break;
            }
        }
    }

    // Any hit: the rays that hit something (a triangle other than their skip, or a voxel).
    std::uint32_t occluded_rays() const { return occluded; }

private:
    // clip_with_axis for the W rays of vector v (the `lanes` of it that are traced), all
    // at once: the same float operations on each lane, so the same segments and entry
    // axes; the per-ray calls were 4 % of a 10^8 overview. Sets tmin, tmax (an empty
    // segment for a lane that misses the cell or is not traced) and axis_in of vector v;
    // returns the lanes that enter the cell. Monotone clipping makes the one test at the
    // end equal to the scalar test after every axis.
    int clip_root(const Box3f& cell, const float (*o)[N], const float (*d)[N], const float* ray_t0,
                  const float* ray_t1, int v, std::uint32_t lanes) {
        const vf slack = vf::broadcast(kSplitSlack), one = vf::broadcast(1.0f), zero = vf::broadcast(0.0f);
        vf t0 = vf::load(ray_t0 + W * v), t1 = vf::load(ray_t1 + W * v);
        vf best = vf::broadcast(-kInf), axis = zero;
        vm in = vm::from_bits(lanes);
        for (int a = 0; a < 3; ++a) {
            const vf dv = vf::load(d[a] + W * v), ov = vf::load(o[a] + W * v);
            const vf lo = vf::broadcast(cell.lo[a]), hi = vf::broadcast(cell.hi[a]);
            const vm flat = dv == zero;
            // A zero component: the origin must lie in the slab, and the axis clips nothing.
            in = andnot(flat & ((ov < lo) | (ov > hi)), in);
            const vf recip = one / dv;
            vf tn = (lo - ov) * recip, tf = (hi - ov) * recip;
            const vm swap = tn > tf;
            const vf near = select(swap, tf, tn), far = select(swap, tn, tf);
            tn = near - abs(near) * slack;
            tf = far + abs(far) * slack;
            t0 = select(flat, t0, select(tn > t0, tn, t0));
            t1 = select(flat, t1, select(tf < t1, tf, t1));
            // The entry axis: the plane the ray enters through last.
            const vf enter = (select(dv > zero, lo, hi) - ov) / dv;
            const vm later = andnot(flat, enter > best);
            best = select(later, enter, best);
            axis = select(later, vf::broadcast(static_cast<float>(a)), axis);
        }
        in = andnot(t0 > t1, in);
        tmin[v] = select(in, t0, vf::broadcast(kInf));
        tmax[v] = select(in, t1, vf::broadcast(-kInf));
        axis_in[v] = select(in, axis, zero);
        return in.bits();
    }

    using NodeRef = lod_detail::NodeRef;
    using Voxel = lod_detail::Voxel;
    enum class Stage : std::uint8_t { Descend, Leaf };

    // Ray i, the one lane left in the subtree at `node`: the single-ray walk takes it
    // through the subtree (the same arithmetic, so the same answer), and the packet goes
    // on with its stack. For packets of mixed signs only: AO frames ran 1.06-1.08x
    // faster with it, primary packets 0.91-0.93x at 10^7 and 10^8 and 1.0x at 10^6
    // (bench/results/ab-lone-walk*.md). The single walk does not pause for memory, and
    // a primary ray's long walk then waits for the treelets that the packets in flight
    // would have overlapped; in core, where the packet step is cheap, the same hand-over
    // cost the AO query 0.82x (kd_detail::OcclusionWalker).
    void walk_lone(LodLane& lane, int i) {
        const int v = i / W, k = i % W;
        alignas(32) float tv[W], tx[W], ax[W];
        tmin[v].store(tv);
        tmax[v].store(tx);
        axis_in[v].store(ax);
        LodHit& h = hits[i];
        const std::uint32_t prim_before = h.prim;
        const bool finished = lod_detail::walk<AnyHit, Quantized>(lane, rays[i], sheared[i], node, tv[k], tx[k],
                                                                  static_cast<int>(ax[k]), voxel, h,
                                                                  skip ? skip[i] : kNoHit);
        if (AnyHit) {
            if (h.prim != prim_before) occluded |= 1u << i;
        } else {
            // The single walk writes input ids; the packet's hits hold block indices
            // until the walk is over (resolve_triangle_ids).
            if (h.tri_block && h.prim != kNoHit && h.prim != kVoxelPrim) h.prim = h.local;
            hit_t[v] = HitV<W>::load(hits + W * v).t;
        }
        if (finished) live[v] = andnot(vm::from_bits(1u << k), live[v]);
    }
    struct Entry {
        NodeRef node;
        Voxel voxel;
        vf tmin[K], tmax[K], axis[K];
    };

    const LodRay* rays = nullptr;
    LodHit* hits = nullptr;
    const std::uint32_t* skip = nullptr;
    ShearedRay sheared[N];
    ShearedRayV<W> sheared_v[K];
    vf inv[3][K], org[3][K], cone_t0[K], tmin[K], tmax[K], axis_in[K], hit_t[K];
    vm live[K], dir_neg[3][K];  // live: rays that may still change their hit
    bool sign_negative[3];      // SharedSigns: the packet's near child is the one its directions leave
    bool lone_walks = false;    // a lane left alone takes the single-ray walk (rays of mixed signs)
    std::uint32_t occluded = 0;
    Entry stack[64];
    int top = 0;
    NodeRef node;
    Voxel voxel{nullptr, 0.0f, 0.0f};
    Stage stage = Stage::Descend;
    LeafPrefetch leaf_;
};
#pragma GCC diagnostic pop

template <int N, bool AnyHit, LodPacketOrder Order, bool Quantized>
inline std::uint32_t packet_walk(LodLane& lane, const Box3f& root_cell, const LodRay* rays, LodHit* hits,
                                 const std::uint32_t* skip, std::uint32_t mask) {
    PacketWalker<N, AnyHit, Order, Quantized, false> walker;
    if (!walker.start(lane, root_cell, rays, hits, skip, mask)) return 0;
    walker.run(lane);
    if constexpr (!AnyHit) resolve_triangle_ids(lane, hits, N);
    return walker.occluded_rays();
}

// A pixel block's primary packet (lod_traverse_packet, lod_trace_packets): it keeps its
// rays and hits in lane order and hands the hits back in row order when done.
template <int N, bool Quantized, bool Yield>
class PrimaryPacket {
    static constexpr int W = packet_width<N>();

public:
    bool start(LodLane& lane, const Box3f& root_cell, const LodRay* rays_in, LodHit* hits_out) {
        hits_out_ = hits_out;
        for (int i = 0; i < N; ++i) rays_[packet_lane<N, W>(i)] = rays_in[i];
        if (walker_.start(lane, root_cell, rays_, hits_, nullptr, N == 32 ? ~0u : (1u << N) - 1)) return true;
        finish(lane);
        return false;
    }
    bool run(LodLane& lane) {
        if (!walker_.run(lane)) return false;
        finish(lane);
        return true;
    }

private:
    void finish(const LodLane& lane) {
        resolve_triangle_ids(lane, hits_, N);
        for (int i = 0; i < N; ++i) hits_out_[i] = hits_[packet_lane<N, W>(i)];
    }
    LodRay rays_[N];
    LodHit hits_[N];
    LodHit* hits_out_ = nullptr;
    PacketWalker<N, false, LodPacketOrder::SharedOrigin, Quantized, Yield> walker_;
};

template <int N, bool Quantized>
inline void traverse_packet(LodLane& lane, const Box3f& root_cell, const LodRay* rays, LodHit* hits) {
    PrimaryPacket<N, Quantized, false> packet;
    if (packet.start(lane, root_cell, rays, hits)) packet.run(lane);
}

template <int N, bool Quantized, int G>
inline void trace_packets(LodLane& lane, const Box3f& root_cell, const LodRay* const* rays, LodHit* const* hits,
                          bool* traced, int count) {
    PrimaryPacket<N, Quantized, true> walkers[G];
    int next = 0;
    walks_in_flight<G>(
        [&](int g) {
            while (next < count) {
                const int j = next++;
                traced[j] = lod_packet_is_coherent<N>(rays[j]);
                if (traced[j] && walkers[g].start(lane, root_cell, rays[j], hits[j])) return true;
            }
            return false;
        },
        [&](int g) { return walkers[g].run(lane); });
}

}  // namespace lod_detail

// The packet walk. Rays (and skips, hits) are in lane order; `mask` selects the rays to
// trace. Closest hit (AnyHit = false): hits[i] gets ray i's hit. Any hit: returns the
// rays that hit something (a triangle other than skip[i], or a voxel); hits are scratch.
// SharedOrigin needs a shared origin; SharedSigns direction components whose signs
// (sign bits, for a zero) agree across the packet; both a shared cone slope.
template <int N, bool AnyHit, LodPacketOrder Order>
inline std::uint32_t lod_packet_walk(LodLane& lane, const Box3f& root_cell, const LodRay* rays, LodHit* hits,
                                     const std::uint32_t* skip, std::uint32_t mask) {
    return lane.quantized_splits
               ? lod_detail::packet_walk<N, AnyHit, Order, true>(lane, root_cell, rays, hits, skip, mask)
               : lod_detail::packet_walk<N, AnyHit, Order, false>(lane, root_cell, rays, hits, skip, mask);
}

// Closest hits of N coherent primary rays given in row order (lod_packet_is_coherent);
// hits_out[i] gets ray i's result.
template <int N>
inline void lod_traverse_packet(LodLane& lane, const Box3f& root_cell, const LodRay* rays, LodHit* hits) {
    if (lane.quantized_splits) {
        lod_detail::traverse_packet<N, true>(lane, root_cell, rays, hits);
    } else {
        lod_detail::traverse_packet<N, false>(lane, root_cell, rays, hits);
    }
}

// The primary packets of `count` pixel blocks (rays[j], hits[j] as in
// lod_traverse_packet), several in flight at once: while one waits for a child treelet
// or a leaf's triangles, the others go on. traced[j] is false for a block whose rays are
// not coherent (lod_packet_is_coherent), which is left to the caller; the others' hits
// are exactly lod_traverse_packet's.
template <int N>
inline void lod_trace_packets(LodLane& lane, const Box3f& root_cell, const LodRay* const* rays,
                              LodHit* const* hits, bool* traced, int count) {
    constexpr int kInFlight = 8;
    if (lane.quantized_splits) {
        lod_detail::trace_packets<N, true, kInFlight>(lane, root_cell, rays, hits, traced, count);
    } else {
        lod_detail::trace_packets<N, false, kInFlight>(lane, root_cell, rays, hits, traced, count);
    }
}

VASTRAY_KERNEL_END
