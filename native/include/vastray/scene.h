// An in-core model ready to ray trace: float geometry relative to the model centre
// (kept in double), optional per-triangle colours, and the structures its rays walk (the
// 8-wide BVH, the kd-tree), each built on first use.
#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <mutex>
#include <vector>

#include "vastray/kdtree.h"
#include "vastray/ray.h"
#include "vastray/wide_bvh.h"

namespace vastray {

struct WorldRay {
    Vec3d org, dir;
    double tmin = 0, tmax = std::numeric_limits<double>::infinity();
};

class Scene {
public:
    // vertices: (V,3) double world coordinates; faces: (F,3) indices; colours: (F,3) RGB8
    // or null; input_ids: per face, the id of that triangle in the input it came from
    // (ingest drops degenerate faces, so face f need not be input triangle f), or null.
    Scene(const double* vertices, std::size_t vertex_count, const std::uint32_t* faces,
          std::size_t face_count, const std::uint8_t* colours, const std::uint32_t* input_ids,
          const KdBuildParams& params);

    // A scene whose tree was built elsewhere (decoded from a built model).
    Scene(const Vec3d& centre, HugeVector<Vec3f>&& tri_vertices, std::vector<std::uint8_t>&& colours, KdTree&& tree)
        : centre_(centre),
          tri_vertices_(std::move(tri_vertices)),
          colours_(std::move(colours)),
          bounds_(tree.bounds),
          tree_(std::move(tree)),
          kd_built_(true) {}

    std::size_t triangle_count() const { return tri_vertices_.size() / 3; }
    bool has_colours() const { return !colours_.empty(); }
    const Vec3d& centre() const { return centre_; }
    // The kd-tree's root cell (model-local): the bounds of the triangles of non-zero area.
    const Box3f& bounds() const { return bounds_; }
    Vec3d world_lo() const { return centre_ + Vec3d(bounds_.lo); }
    Vec3d world_hi() const { return centre_ + Vec3d(bounds_.hi); }
    // The kd-tree, built on first use with the parameters the scene was made with. By
    // default no ray of the renderer walks it (the wide BVH serves them all), so a scene
    // made to be rendered never pays for it: at 10^7 triangles 6-7 s and about 250 MB. Like
    // wide_bvh(), it is built on the pool: asked for from inside a ThreadPool task before
    // it is built, it throws std::logic_error rather than wait on itself.
    const KdTree& tree() const {
        if (!kd_built_.load(std::memory_order_acquire)) build_tree();
        return tree_;
    }
    bool kd_tree_built() const { return kd_built_.load(std::memory_order_acquire); }
    // The 8-wide BVH for secondary rays (wide_bvh.h), built on first use (not from inside
    // a ThreadPool task: the build runs on the pool); null for a scene too large for it.
    const WideBvh* wide_bvh() const;
    bool fits_wide_bvh() const { return triangle_count() <= WideNode::kMaxFirst; }
    const Vec3f* tri_vertices() const { return tri_vertices_.data(); }
    const std::uint8_t* colour(std::uint32_t prim) const { return colours_.data() + 3 * static_cast<std::size_t>(prim); }
    // The input's id of triangle `prim`: what frames and ray queries report.
    std::uint32_t input_id(std::uint32_t prim) const { return input_ids_.empty() ? prim : input_ids_[prim]; }
    // Geometry, colours, ids and the kd-tree where it is built (not the wide BVH).
    std::size_t memory_bytes() const;

    // Converts a world ray to model-local float. The subtraction of the centre happens
    // in double, so a model 1e7 units from the origin keeps float precision locally.
    // (Inline, like normal(): the kernels call both for every pixel, and a call out of
    // their AVX code into the SSE2 core cost 5 % of a 10^7 frame.)
    Ray to_local(const WorldRay& r) const {
        Ray ray;
        ray.org = Vec3f(r.org - centre_);
        ray.dir = Vec3f(r.dir);
        ray.tmin = static_cast<float>(r.tmin);
        ray.tmax = static_cast<float>(r.tmax);
        return ray;
    }

    // Geometric normal (unnormalised orientation of the stored winding), local frame.
    Vec3f normal(std::uint32_t prim) const {
        const Vec3f* v = tri_vertices_.data() + 3 * static_cast<std::size_t>(prim);
        return cross(v[1] - v[0], v[2] - v[0]);
    }

private:
    void build_tree() const;

    Vec3d centre_;
    HugeVector<Vec3f> tri_vertices_;  // 3 per triangle, model-local
    std::vector<std::uint8_t> colours_;
    std::vector<std::uint32_t> input_ids_;  // empty: the identity
    Box3f bounds_;
    KdBuildParams kd_params_;
    mutable std::once_flag kd_once_;
    mutable KdTree tree_;
    mutable std::atomic<bool> kd_built_{false};
    mutable std::once_flag wide_once_;
    mutable std::unique_ptr<WideBvh> wide_;
};

// Batch queries in world coordinates (tools and tests). Outputs are arrays of n. They
// run on the active ISA path (isa.h), like frames.
struct BatchResult {
    std::vector<double> t;
    std::vector<std::int64_t> prim;  // input triangle id
    std::vector<float> u, v;
    std::vector<float> normal;  // 3 per ray: unit geometric normal (0 on a miss)
    TraversalCounters counters;
};
struct SectionPlane;
// Section planes cut as in rendering (render.h): a ray entering a cut solid through a
// plane hits its cap (t on the plane, the plane's normal, the solid's triangle).
BatchResult intersect_batch(const Scene& scene, const double* origins, const double* directions,
                            const double* tmin, const double* tmax, std::size_t n, unsigned threads,
                            const std::vector<SectionPlane>& sections = {});
std::vector<std::uint8_t> occluded_batch(const Scene& scene, const double* origins,
                                         const double* directions, const double* tmin,
                                         const double* tmax, std::size_t n, unsigned threads);

// Independent reference: double-precision Möller-Trumbore against every triangle, no
// acceleration structure. Also returns the second-closest distance so callers can tell
// ties (two triangles at the same t) from real disagreements. `cull` skips runs of
// triangles whose widened double bounding box the ray misses (same answers, faster).
struct ReferenceResult {
    std::vector<double> t, t_second, u, v;
    std::vector<std::int64_t> prim;
};
ReferenceResult reference_intersect(const double* vertices, std::size_t vertex_count,
                                    const std::uint32_t* faces, std::size_t face_count,
                                    const double* origins, const double* directions,
                                    const double* tmin, const double* tmax, std::size_t n,
                                    unsigned threads, bool cull = true);

}  // namespace vastray
