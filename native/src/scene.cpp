#include "vastray/scene.h"

#include <stdexcept>
#include <string>

#include "vastray/thread_pool.h"

namespace vastray {

Scene::Scene(const double* vertices, std::size_t vertex_count, const std::uint32_t* faces,
             std::size_t face_count, const std::uint8_t* colours, const std::uint32_t* input_ids,
             const KdBuildParams& params)
    : kd_params_(params) {
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
            const Vec3f local(p - centre_);
            if (!all_finite(local)) {
                throw std::invalid_argument("vertex " + std::to_string(vi) +
                                            " lies too far from the model's centre for float coordinates "
                                            "(the model spans more than the float range)");
            }
            tri_vertices_[3 * f + static_cast<std::size_t>(k)] = local;
        }
        // The bounds the kd-tree's build takes for its root cell (build_kdtree): of the
        // triangles with area.
        const Vec3f* v = tri_vertices_.data() + 3 * f;
        if (has_area(v[0], v[1], v[2])) {
            for (int k = 0; k < 3; ++k) bounds_.extend(v[k]);
        }
    }
    if (bounds_.empty()) bounds_ = Box3f{{0, 0, 0}, {0, 0, 0}};
    if (colours != nullptr) colours_.assign(colours, colours + 3 * face_count);
    if (input_ids != nullptr) input_ids_.assign(input_ids, input_ids + face_count);
}

void Scene::build_tree() const {
    if (ThreadPool::in_task()) {
        throw std::logic_error("the scene's kd-tree was first asked for inside a thread-pool task; "
                               "its build runs on the pool, so build it before the parallel loop");
    }
    std::call_once(kd_once_, [this] {
        tree_ = build_kdtree(TriangleSoup{tri_vertices_.data(), triangle_count()}, kd_params_);
        kd_built_.store(true, std::memory_order_release);
    });
}

const WideBvh* Scene::wide_bvh() const {
    if (!fits_wide_bvh()) return nullptr;
    std::call_once(wide_once_, [this] {
        wide_ = std::make_unique<WideBvh>(build_wide_bvh(tri_vertices_.data(), triangle_count(), 0));
    });
    return wide_.get();
}

std::size_t Scene::memory_bytes() const {
    return tri_vertices_.size() * sizeof(Vec3f) + colours_.size() + 4 * input_ids_.size() +
           (kd_tree_built() ? tree_.memory_bytes() : 0);
}

}  // namespace vastray
