// Watertight ray/triangle intersection (Woop, Benthin, Wald, JCGT 2013).
//
// The ray is sheared so it runs along +z; the triangle's 2D edge functions are then
// evaluated in float and, when one is exactly zero (the ray passes through an edge or
// a vertex), re-evaluated in double so neighbouring triangles agree on which of them
// owns the edge. No epsilon: a ray through a shared edge hits at least one side.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>
#include <utility>

#include "vastray/isa.h"
#include "vastray/ray.h"

VASTRAY_KERNEL_BEGIN

// Per-ray shear constants, computed once per ray.
struct ShearedRay {
    int kx = 0, ky = 1, kz = 2;
    float sx = 0, sy = 0, sz = 1;

    ShearedRay() = default;
    explicit ShearedRay(const Vec3f& d) {
        const float ax = std::abs(d.x), ay = std::abs(d.y), az = std::abs(d.z);
        kz = ax > ay ? (ax > az ? 0 : 2) : (ay > az ? 1 : 2);
        kx = kz == 2 ? 0 : kz + 1;
        ky = kx == 2 ? 0 : kx + 1;
        if (d[kz] < 0) std::swap(kx, ky);  // keep the winding, so the sign test stays meaningful
        sx = d[kx] / d[kz];
        sy = d[ky] / d[kz];
        sz = 1.0f / d[kz];
    }
};

// Tests [tmin, hit.t); on a hit updates hit.t/u/v and returns true (prim is left to the caller).
// Always inlined: out of line (GCC's choice) each triangle of a single ray's leaf cost a
// call (batch rays 1.04x, out-of-core frames 1.03x inlined; docs/native-core.md).
[[gnu::always_inline]] inline bool intersect_triangle(const Ray& ray, const ShearedRay& s, const Vec3f& p0,
                                                     const Vec3f& p1, const Vec3f& p2, Hit& hit) {
    const Vec3f a = p0 - ray.org, b = p1 - ray.org, c = p2 - ray.org;
    const float ax = a[s.kx] - s.sx * a[s.kz], ay = a[s.ky] - s.sy * a[s.kz];
    const float bx = b[s.kx] - s.sx * b[s.kz], by = b[s.ky] - s.sy * b[s.kz];
    const float cx = c[s.kx] - s.sx * c[s.kz], cy = c[s.ky] - s.sy * c[s.kz];
    float u = cx * by - cy * bx;
    float v = ax * cy - ay * cx;
    float w = bx * ay - by * ax;
    if (u == 0.0f || v == 0.0f || w == 0.0f) {
        // Exactly on an edge in float: decide in double (the products are then exact).
        u = static_cast<float>(static_cast<double>(cx) * by - static_cast<double>(cy) * bx);
        v = static_cast<float>(static_cast<double>(ax) * cy - static_cast<double>(ay) * cx);
        w = static_cast<float>(static_cast<double>(bx) * ay - static_cast<double>(by) * ax);
    }
    if ((u < 0 || v < 0 || w < 0) && (u > 0 || v > 0 || w > 0)) return false;
    const float det = u + v + w;
    if (det == 0.0f) return false;
    const float az = s.sz * a[s.kz], bz = s.sz * b[s.kz], cz = s.sz * c[s.kz];
    const float t_scaled = u * az + v * bz + w * cz;
    // Compare t = t_scaled / det against [tmin, hit.t) without dividing.
    const float sign = det < 0 ? -1.0f : 1.0f;
    const float abs_det = std::abs(det);
    const float ts = t_scaled * sign;
    if (ts < ray.tmin * abs_det || !(ts < hit.t * abs_det)) return false;
    const float inv_det = 1.0f / det;
    const float t = t_scaled * inv_det;
    if (!(t < hit.t) || t < ray.tmin) return false;
    hit.t = t;
    hit.u = v * inv_det;
    hit.v = w * inv_det;
    return true;
}

VASTRAY_KERNEL_END
