// Pieces every packet kernel shares (in core and out of core): rays and hits of a
// packet in SIMD registers, the watertight triangle test on W rays at once, and the
// order in which a pixel block's rays fill the vectors.
//
// The vector test repeats triangle.h's float operations in the same order, so each lane
// gets bit for bit the single-ray answer; a lane whose edge functions are exactly zero
// (the ray passes through an edge in float) is finished by the scalar test, which
// decides in double. Packets therefore change speed, never answers.
#pragma once

#include <cstdint>
#include <limits>

#include "vastray/isa.h"
#include "vastray/simd.h"
#include "vastray/triangle.h"

VASTRAY_KERNEL_BEGIN

// Vector width for a packet of N rays: the build's widest that the packet fills (16-ray
// blocks take one AVX-512 vector or two AVX ones, 8-ray packets one AVX vector), SSE
// for 2x2 quads.
template <int N>
constexpr int packet_width() {
    if constexpr (N >= simd::kWidth) {
        return simd::kWidth;
    } else {
        return N >= 8 && simd::kWidth >= 8 ? 8 : 4;
    }
}

// Ray i of a Side x Side block (row order) goes to lane packet_lane<N, W>(i). Vectors of
// four rays take a 2x2 quad each (more coherent than a row of four); vectors of eight
// take two rows of four.
template <int N, int W>
constexpr int packet_lane(int i) {
    if constexpr (N == 16 && W == 4) {
        const int x = i % 4, y = i / 4;
        return 4 * (2 * (y / 2) + x / 2) + 2 * (y % 2) + x % 2;
    } else {
        return i;
    }
}

// The geometric ray of a packet's ray type (Ray, or LodRay with its cone).
inline const Ray& ray_of(const Ray& r) { return r; }
template <typename R>
inline const Ray& ray_of(const R& r) {
    return r.ray;
}

// The closest hits of W rays, structure of arrays (prim as integer bit patterns).
template <int W>
struct HitV {
    using vf = simd::vfloat<W>;
    vf t, u, v, prim;

    // Load and store the t, u, v and prim of W hits (Hit or a type derived from it,
    // whose other fields are left alone).
    template <typename H>
    static HitV load(const H* h) {
        alignas(32) float t_[W], u_[W], v_[W], p_[W];
        for (int k = 0; k < W; ++k) {
            t_[k] = h[k].t;
            u_[k] = h[k].u;
            v_[k] = h[k].v;
            std::memcpy(p_ + k, &h[k].prim, sizeof(float));
        }
        return {vf::load(t_), vf::load(u_), vf::load(v_), vf::load(p_)};
    }
    template <typename H>
    void store(H* h) const {
        alignas(32) float t_[W], u_[W], v_[W], p_[W];
        t.store(t_);
        u.store(u_);
        v.store(v_);
        prim.store(p_);
        for (int k = 0; k < W; ++k) {
            h[k].t = t_[k];
            h[k].u = u_[k];
            h[k].v = v_[k];
            std::memcpy(&h[k].prim, p_ + k, sizeof(float));
        }
    }
};

// W rays in the shear frames of the watertight test, for testing one triangle against
// them at once. Each lane keeps its own permutation (kx, ky, kz): the AO rays of a point
// point every way. Built once per packet.
template <int W>
struct ShearedRayV {
    using vf = simd::vfloat<W>;
    using vm = simd::vmask<W>;
    int kx = 0, ky = 1, kz = 2;  // the permutation, when every lane has the same
    bool uniform = true;
    vm x_is[2], y_is[2], z_is[2];  // else: lanes whose kx (ky, kz) is axis 0, axis 1
    vf ox, oy, oz;                 // origins, permuted into each lane's shear frame
    vf sx, sy, sz;
    vf tmin;

    ShearedRayV() = default;
    template <typename RayT>
    ShearedRayV(const RayT* rays, const ShearedRay* sheared) {
        for (int k = 1; k < W; ++k) {
            uniform = uniform && sheared[k].kx == sheared[0].kx && sheared[k].ky == sheared[0].ky &&
                      sheared[k].kz == sheared[0].kz;
        }
        kx = sheared[0].kx;
        ky = sheared[0].ky;
        kz = sheared[0].kz;
        alignas(32) float a[7][W];
        unsigned is[3][2] = {{0, 0}, {0, 0}, {0, 0}};
        for (int k = 0; k < W; ++k) {
            const Ray& ray = ray_of(rays[k]);
            const int perm[3] = {sheared[k].kx, sheared[k].ky, sheared[k].kz};
            for (int c = 0; c < 3; ++c) {
                a[c][k] = ray.org[perm[c]];
                for (int axis = 0; axis < 2; ++axis) is[c][axis] |= (perm[c] == axis ? 1u : 0u) << k;
            }
            a[3][k] = sheared[k].sx;
            a[4][k] = sheared[k].sy;
            a[5][k] = sheared[k].sz;
            a[6][k] = ray.tmin;
        }
        for (int axis = 0; axis < 2; ++axis) {
            x_is[axis] = vm::from_bits(is[0][axis]);
            y_is[axis] = vm::from_bits(is[1][axis]);
            z_is[axis] = vm::from_bits(is[2][axis]);
        }
        ox = vf::load(a[0]);
        oy = vf::load(a[1]);
        oz = vf::load(a[2]);
        sx = vf::load(a[3]);
        sy = vf::load(a[4]);
        sz = vf::load(a[5]);
        tmin = vf::load(a[6]);
    }

    // Component c (0: kx, 1: ky, 2: kz) of point p in each lane's frame.
    vf coord(const Vec3f& p, int c) const {
        if (uniform) return vf::broadcast(p[c == 0 ? kx : c == 1 ? ky : kz]);
        const vm* is = c == 0 ? x_is : c == 1 ? y_is : z_is;
        return select(is[0], vf::broadcast(p.x), select(is[1], vf::broadcast(p.y), vf::broadcast(p.z)));
    }
};

// The lanes `edge` of intersect_triangle_v, whose rays pass exactly through an edge in
// float: decided in double, lane by lane (rare; out of line, so the test stays small).
template <int W, typename RayT>
[[gnu::noinline]] int intersect_triangle_edges(const RayT* rays, const ShearedRay* sheared, const Vec3f& p0,
                                               const Vec3f& p1, const Vec3f& p2, std::uint32_t id, int edge,
                                               HitV<W>& hit) {
    int changed = 0;
    Hit lanes[W];
    hit.store(lanes);
    for (int k = 0; k < W; ++k) {
        if ((edge >> k & 1) && intersect_triangle(ray_of(rays[k]), sheared[k], p0, p1, p2, lanes[k])) {
            lanes[k].prim = id;
            changed |= 1 << k;
        }
    }
    hit = HitV<W>::load(lanes);
    return changed;
}

// The watertight test of triangle.h on W rays at once; `active` marks the lanes to
// test. Returns the lanes whose hit changed. Always inlined: the walks call it for every
// triangle of a leaf, and a call from their AVX loops costs a vzeroupper and the
// spilling of every vector they keep in registers.
template <int W, typename RayT>
[[gnu::always_inline]] inline int intersect_triangle_v(const ShearedRayV<W>& r, const RayT* rays,
                                                       const ShearedRay* sheared, const Vec3f& p0, const Vec3f& p1,
                                                       const Vec3f& p2, std::uint32_t id, simd::vmask<W> active,
                                                       HitV<W>& hit) {
    using vf = simd::vfloat<W>;
    using vm = simd::vmask<W>;
    const vf zero = vf::broadcast(0.0f);
    const vf ax0 = r.coord(p0, 0) - r.ox, ay0 = r.coord(p0, 1) - r.oy, az0 = r.coord(p0, 2) - r.oz;
    const vf bx0 = r.coord(p1, 0) - r.ox, by0 = r.coord(p1, 1) - r.oy, bz0 = r.coord(p1, 2) - r.oz;
    const vf cx0 = r.coord(p2, 0) - r.ox, cy0 = r.coord(p2, 1) - r.oy, cz0 = r.coord(p2, 2) - r.oz;
    const vf ax = ax0 - r.sx * az0, ay = ay0 - r.sy * az0;
    const vf bx = bx0 - r.sx * bz0, by = by0 - r.sy * bz0;
    const vf cx = cx0 - r.sx * cz0, cy = cy0 - r.sy * cz0;
    const vf u = cx * by - cy * bx;
    const vf v = ax * cy - ay * cx;
    const vf w = bx * ay - by * ax;
    const vm on_edge = active & ((u == zero) | (v == zero) | (w == zero));
    const vm any_neg = (u < zero) | (v < zero) | (w < zero);
    const vm any_pos = (u > zero) | (v > zero) | (w > zero);
    const vf det = u + v + w;
    vm valid = andnot(on_edge | (any_neg & any_pos), active) & (det != zero);
    int changed = 0;
    if (valid.bits() != 0) {
        const vf az = r.sz * az0, bz = r.sz * bz0, cz = r.sz * cz0;
        const vf t_scaled = u * az + v * bz + w * cz;
        const vf abs_det = abs(det);
        const vf ts = t_scaled ^ sign_bits(det);
        valid = andnot(ts < r.tmin * abs_det, valid) & (ts < hit.t * abs_det);
        if (valid.bits() != 0) {
            const vf inv_det = vf::broadcast(1.0f) / det;
            const vf t = t_scaled * inv_det;
            valid = andnot(t < r.tmin, valid & (t < hit.t));
            hit.t = select(valid, t, hit.t);
            hit.u = select(valid, v * inv_det, hit.u);
            hit.v = select(valid, w * inv_det, hit.v);
            hit.prim = select(valid, vf::bits(id), hit.prim);
            changed = valid.bits();
        }
    }
    if (const int edge = on_edge.bits(); edge != 0) {
        changed |= intersect_triangle_edges<W>(rays, sheared, p0, p1, p2, id, edge, hit);
    }
    return changed;
}

// A packet's segments in the two children of a kd split: for each of its K vectors of
// W lanes, the single-ray cases of traverse() lane by lane ([tmin, first_hi] in a ray's
// own first child, its origin's side; [second_lo, tmax] in its second), mapped to the
// packet's order, whose near child is the left one when near_left is set. `may_flip`
// false promises that every lane's own first child is the packet's near one. A segment
// is empty when lo > hi; near_in / far_in are the active lanes with a segment there.
template <int W, int K>
struct PacketSplit {
    using vf = simd::vfloat<W>;
    using vm = simd::vmask<W>;
    vf near_lo[K], near_hi[K], far_lo[K], far_hi[K];
    vm near_in[K], far_in[K];
    int any_near = 0, any_far = 0;

    PacketSplit(float split, bool near_left, bool may_flip, const vf* org, const vf* inv, const vm* dir_negative,
                const vf* tmin, const vf* tmax, const vm* active) {
        // Apart from origins on the plane, every lane's first child is the packet's near
        // one: no lane flips, and the selects that would map flipped lanes are left out.
        if (may_flip) {
            compute<true>(split, near_left, org, inv, dir_negative, tmin, tmax, active);
        } else {
            compute<false>(split, near_left, org, inv, dir_negative, tmin, tmax, active);
        }
    }

private:
    template <bool MayFlip>
    void compute(float split, bool near_left, const vf* org, const vf* inv, const vm* dir_negative, const vf* tmin,
                 const vf* tmax, const vm* active) {
        const vf split_v = vf::broadcast(split);
        const vf zero = vf::broadcast(0.0f), inf = vf::broadcast(std::numeric_limits<float>::infinity());
        constexpr int kAllLanes = (1 << W) - 1;
        for (int v = 0; v < K; ++v) {
            const vf t_split = (split_v - org[v]) * inv[v];
            vf first_hi, second_lo;
            // With a shared origin off the plane, whether the plane lies ahead depends only
            // on the direction sign, which a primary packet's lanes share: a plane ahead of
            // every lane at a finite distance (the usual case) needs none of the selects
            // below, and the branch predicts well. The arithmetic is theirs for such lanes
            // (|t_split| = t_split). Rays from many origins mix lanes with the plane behind.
            if (!MayFlip && ((t_split > zero) & (t_split < inf)).bits() == kAllLanes) {
                const vf slack = t_split * vf::broadcast(kSplitSlack);
                first_hi = min(t_split + slack, tmax[v]);
                second_lo = max(t_split - slack, tmin[v]);
            } else {
                const vf abs_split = abs(t_split);
                // An infinite t_split (zero direction component) gets no slack: inf - inf is NaN.
                const vf slack = select(abs_split < inf, abs_split * vf::broadcast(kSplitSlack), zero);
                const vf ts_lo = t_split - slack, ts_hi = t_split + slack;
                const vm nan = t_split != t_split;
                const vm behind = t_split <= zero;
                first_hi = select(nan | behind, tmax[v], min(ts_hi, tmax[v]));
                second_lo = select(nan, tmin[v], select(behind, inf, max(ts_lo, tmin[v])));
            }
            if constexpr (MayFlip) {
                // Lanes whose own first child is the packet's far one: origin across the
                // plane, or exactly on it with the other direction sign.
                const vm near_left_v = vm::from_bits(near_left ? ~0u : 0u);
                const vm flip = ((org[v] < split_v) | ((org[v] == split_v) & dir_negative[v])) ^ near_left_v;
                near_lo[v] = select(flip, second_lo, tmin[v]);
                near_hi[v] = select(flip, tmax[v], first_hi);
                far_lo[v] = select(flip, tmin[v], second_lo);
                far_hi[v] = select(flip, first_hi, tmax[v]);
            } else {
                near_lo[v] = tmin[v];
                near_hi[v] = first_hi;
                far_lo[v] = second_lo;
                far_hi[v] = tmax[v];
            }
            near_in[v] = active[v] & (near_lo[v] <= near_hi[v]);
            far_in[v] = active[v] & (far_lo[v] <= far_hi[v]);
            any_near |= near_in[v].bits();
            any_far |= far_in[v].bits();
        }
    }
};

VASTRAY_KERNEL_END
