#include "vastray/scene.h"

#include <stdexcept>
#include <string>

#include "vastray/thread_pool.h"

namespace vastray {

Scene::Scene(const double* vertices, std::size_t vertex_count, const std::uint32_t* faces,
             std::size_t face_count, const std::uint8_t* colours, const std::uint32_t* input_ids,
             const KdBuildParams& params) {
    if (face_count == 0) throw std::invalid_argument("scene has no triangles");
    Vec3d lo(std::numeric_limits<double>::infinity(), std::numeric_limits<double>::infinity(),
             std::numeric_limits<double>::infinity());
    Vec3d hi = -lo;
    for (std::size_t i = 0; i < vertex_count; ++i) {
        const Vec3d p(vertices[3 * i], vertices[3 * i + 1], vertices[3 * i + 2]);
        if (!all_finite(p)) throw std::invalid_argument("vertex " + std::to_string(i) + " is not finite");
        lo = vmin(lo, p);
        hi = vmax(hi, p);
    }
    centre_ = (lo + hi) * 0.5;
    tri_vertices_.resize(3 * face_count);
    for (std::size_t f = 0; f < face_count; ++f) {
        for (int k = 0; k < 3; ++k) {
            const std::uint32_t vi = faces[3 * f + static_cast<std::size_t>(k)];
            if (vi >= vertex_count) {
                throw std::invalid_argument("face " + std::to_string(f) + " references vertex " +
                                            std::to_string(vi) + " of " + std::to_string(vertex_count));
            }
            const Vec3d p(vertices[3 * vi], vertices[3 * vi + 1], vertices[3 * vi + 2]);
            tri_vertices_[3 * f + static_cast<std::size_t>(k)] = Vec3f(p - centre_);
        }
    }
    if (colours != nullptr) colours_.assign(colours, colours + 3 * face_count);
    if (input_ids != nullptr) input_ids_.assign(input_ids, input_ids + face_count);
    tree_ = build_kdtree(TriangleSoup{tri_vertices_.data(), face_count}, params);
}

std::size_t Scene::memory_bytes() const {
    return tri_vertices_.size() * sizeof(Vec3f) + colours_.size() + 4 * input_ids_.size() + tree_.memory_bytes();
}

Ray Scene::to_local(const WorldRay& r) const {
    Ray ray;
    ray.org = Vec3f(r.org - centre_);
    ray.dir = Vec3f(r.dir);
    ray.tmin = static_cast<float>(r.tmin);
    ray.tmax = static_cast<float>(r.tmax);
    return ray;
}

Vec3f Scene::normal(std::uint32_t prim) const {
    const Vec3f* v = tri_vertices_.data() + 3 * static_cast<std::size_t>(prim);
    return cross(v[1] - v[0], v[2] - v[0]);
}

namespace {

WorldRay load_ray(const double* origins, const double* directions, const double* tmin,
                  const double* tmax, std::size_t i) {
    WorldRay r;
    r.org = {origins[3 * i], origins[3 * i + 1], origins[3 * i + 2]};
    r.dir = {directions[3 * i], directions[3 * i + 1], directions[3 * i + 2]};
    r.tmin = tmin[i];
    r.tmax = tmax[i];
    return r;
}

bool ray_is_valid(const WorldRay& r) {
    return all_finite(r.org) && all_finite(r.dir) && dot(r.dir, r.dir) > 0 && !std::isnan(r.tmin) &&
           !std::isnan(r.tmax);
}

constexpr std::size_t kBatch = 1024;

}  // namespace

BatchResult intersect_batch(const Scene& scene, const double* origins, const double* directions,
                            const double* tmin, const double* tmax, std::size_t n, unsigned threads) {
    BatchResult out;
    out.t.assign(n, std::numeric_limits<double>::infinity());
    out.prim.assign(n, -1);
    out.u.assign(n, 0.0f);
    out.v.assign(n, 0.0f);
    out.normal.assign(3 * n, 0.0f);
    ThreadPool& pool = ThreadPool::global();
    std::vector<TraversalCounters> lane_counters(pool.lanes());
    pool.parallel_for((n + kBatch - 1) / kBatch, [&](std::size_t b, unsigned lane) {
        TraversalCounters& c = lane_counters[lane];
        for (std::size_t i = b * kBatch; i < std::min(n, (b + 1) * kBatch); ++i) {
            const WorldRay wr = load_ray(origins, directions, tmin, tmax, i);
            if (!ray_is_valid(wr)) continue;  // invalid rays report a miss
            Hit hit;
            if (scene.trace<false>(scene.to_local(wr), hit, c)) {
                out.t[i] = hit.t;
                out.prim[i] = scene.input_id(hit.prim);
                out.u[i] = hit.u;
                out.v[i] = hit.v;
                const Vec3f nrm = normalize(scene.normal(hit.prim));
                for (int a = 0; a < 3; ++a) out.normal[3 * i + static_cast<std::size_t>(a)] = nrm[a];
            }
        }
    }, threads);
    for (const auto& c : lane_counters) {
        out.counters.node_visits += c.node_visits;
        out.counters.triangle_tests += c.triangle_tests;
    }
    return out;
}

std::vector<std::uint8_t> occluded_batch(const Scene& scene, const double* origins,
                                         const double* directions, const double* tmin,
                                         const double* tmax, std::size_t n, unsigned threads) {
    std::vector<std::uint8_t> out(n, 0);
    ThreadPool& pool = ThreadPool::global();
    pool.parallel_for((n + kBatch - 1) / kBatch, [&](std::size_t b, unsigned) {
        TraversalCounters c;
        for (std::size_t i = b * kBatch; i < std::min(n, (b + 1) * kBatch); ++i) {
            const WorldRay wr = load_ray(origins, directions, tmin, tmax, i);
            if (!ray_is_valid(wr)) continue;
            Hit hit;
            out[i] = scene.trace<true>(scene.to_local(wr), hit, c) ? 1 : 0;
        }
    }, threads);
    return out;
}

}  // namespace vastray
