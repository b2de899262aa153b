// Brute-force double-precision reference for tests. Deliberately shares nothing with
// the kd-tree or the watertight test: a different algorithm (Möller-Trumbore) in a
// different precision over every triangle.
#include <algorithm>

#include "vastray/scene.h"
#include "vastray/thread_pool.h"

namespace vastray {

ReferenceResult reference_intersect(const double* vertices, std::size_t vertex_count,
                                    const std::uint32_t* faces, std::size_t face_count,
                                    const double* origins, const double* directions,
                                    const double* tmin, const double* tmax, std::size_t n,
                                    unsigned threads, bool cull) {
    const double inf = std::numeric_limits<double>::infinity();
    ReferenceResult out;
    out.t.assign(n, inf);
    out.t_second.assign(n, inf);
    out.u.assign(n, 0);
    out.v.assign(n, 0);
    out.prim.assign(n, -1);
    for (std::size_t f = 0; f < 3 * face_count; ++f) {
        if (faces[f] >= vertex_count) throw std::invalid_argument("face index out of range");
    }
    auto vert = [&](std::uint32_t i) { return Vec3d(vertices[3 * i], vertices[3 * i + 1], vertices[3 * i + 2]); };
    // Edges are precomputed once: the brute-force loop is the whole cost of the tests
    // that use this reference.
    struct Tri {
        Vec3d p0, e1, e2;
    };
    std::vector<Tri> tris(face_count);
    for (std::size_t f = 0; f < face_count; ++f) {
        const Vec3d p0 = vert(faces[3 * f]);
        tris[f] = {p0, vert(faces[3 * f + 1]) - p0, vert(faces[3 * f + 2]) - p0};
    }
    // Optional culling: triangles in file order are cut into runs of kRun, each with a
    // double bounding box widened by a margin; a run is skipped only when the ray misses
    // the widened box. That keeps the reference trivially correct while making 1e5 rays
    // against 1e5 triangles affordable in a test.
    constexpr std::size_t kRun = 32;
    std::vector<std::size_t> order(face_count);
    for (std::size_t f = 0; f < face_count; ++f) order[f] = f;
    if (cull) {
        // Sort by a coarse spatial key so runs are compact in space.
        Vec3d lo(std::numeric_limits<double>::infinity(), std::numeric_limits<double>::infinity(),
                 std::numeric_limits<double>::infinity());
        Vec3d hi = -lo;
        for (const Tri& t : tris) { lo = vmin(lo, t.p0); hi = vmax(hi, t.p0); }
        const Vec3d ext = vmax(hi - lo, Vec3d(1e-300, 1e-300, 1e-300));
        std::vector<std::uint64_t> key(face_count);
        for (std::size_t f = 0; f < face_count; ++f) {
            std::uint64_t k = 0;
            const Vec3d q = (tris[f].p0 - lo) * Vec3d(1023.0 / ext.x, 1023.0 / ext.y, 1023.0 / ext.z);
            for (int bit = 9; bit >= 0; --bit) {
                for (int a = 0; a < 3; ++a) k = (k << 1) | ((static_cast<std::uint64_t>(q[a]) >> bit) & 1u);
            }
            key[f] = k;
        }
        std::sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return key[a] < key[b]; });
    }
    const std::size_t runs = (face_count + kRun - 1) / kRun;
    std::vector<Vec3d> run_lo(runs), run_hi(runs);
    for (std::size_t r = 0; r < runs; ++r) {
        Vec3d lo(std::numeric_limits<double>::infinity(), std::numeric_limits<double>::infinity(),
                 std::numeric_limits<double>::infinity());
        Vec3d hi = -lo;
        for (std::size_t k = r * kRun; k < std::min(face_count, (r + 1) * kRun); ++k) {
            const Tri& t = tris[order[k]];
            for (const Vec3d& p : {t.p0, t.p0 + t.e1, t.p0 + t.e2}) { lo = vmin(lo, p); hi = vmax(hi, p); }
        }
        const double margin = 1e-9 * std::max({length(lo), length(hi), length(hi - lo)});
        run_lo[r] = lo - Vec3d(margin, margin, margin);
        run_hi[r] = hi + Vec3d(margin, margin, margin);
    }
    ThreadPool::global().parallel_for((n + 63) / 64, [&](std::size_t b, unsigned) {
        for (std::size_t i = b * 64; i < std::min(n, (b + 1) * 64); ++i) {
            const Vec3d o(origins[3 * i], origins[3 * i + 1], origins[3 * i + 2]);
            const Vec3d d(directions[3 * i], directions[3 * i + 1], directions[3 * i + 2]);
            double best = inf, second = inf, bu = 0, bv = 0;
            std::int64_t prim = -1;
            for (std::size_t r = 0; r < runs; ++r) {
                if (cull) {
                    double t0 = -inf, t1 = inf;
                    bool miss = false;
                    for (int a = 0; a < 3 && !miss; ++a) {
                        if (d[a] == 0) {
                            miss = o[a] < run_lo[r][a] || o[a] > run_hi[r][a];
                            continue;
                        }
                        double ta = (run_lo[r][a] - o[a]) / d[a], tb = (run_hi[r][a] - o[a]) / d[a];
                        if (ta > tb) std::swap(ta, tb);
                        t0 = std::max(t0, ta);
                        t1 = std::min(t1, tb);
                        miss = t0 > t1 * (1 + 1e-12) + 1e-300;
                    }
                    if (miss || t1 < tmin[i] || t0 > std::min(tmax[i], second) * (1 + 1e-9)) continue;
                }
                for (std::size_t k = r * kRun; k < std::min(face_count, (r + 1) * kRun); ++k) {
                    const std::size_t f = order[k];
                    const Vec3d &p0 = tris[f].p0, &e1 = tris[f].e1, &e2 = tris[f].e2;
                    const Vec3d pv = cross(d, e2);
                    const double det = dot(e1, pv);
                    if (det == 0) continue;
                    const double inv = 1.0 / det;
                    const Vec3d tv = o - p0;
                    const double u = dot(tv, pv) * inv;
                    if (u < 0 || u > 1) continue;
                    const Vec3d qv = cross(tv, e1);
                    const double v = dot(d, qv) * inv;
                    if (v < 0 || u + v > 1) continue;
                    const double t = dot(e2, qv) * inv;
                    if (t < tmin[i] || t > tmax[i]) continue;
                    if (t < best || (t == best && static_cast<std::int64_t>(f) < prim)) {
                        if (t < best) second = best;
                        best = t;
                        bu = u;
                        bv = v;
                        prim = static_cast<std::int64_t>(f);
                    } else if (t < second) {
                        second = t;
                    }
                }
            }
            out.t[i] = best;
            out.t_second[i] = second;
            out.u[i] = bu;
            out.v[i] = bv;
            out.prim[i] = prim;
        }
    }, threads);
    return out;
}

}  // namespace vastray
