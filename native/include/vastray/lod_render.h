// Frames and ray queries of a built model rendered from the block cache with level of
// detail. Neither ever waits for data: what is missing is requested, and the stats say
// whether the answer was complete.
#pragma once

#include <memory>

#include "vastray/block_cache.h"
#include "vastray/render.h"

namespace vastray {

Frame render_lod(BlockCache& cache, CachedModel& model, const Camera& camera, const RenderParams& params);

// Full-detail closest hits of world-space rays (picking, measuring). A ray whose answer
// needs a block that is not cached yet gets complete[i] = 0 (its block is requested);
// ask again once fetches finish.
struct LodRayHits {
    std::vector<double> t, position;  // position: 3 per ray, world frame (double)
    std::vector<float> normal;        // 3 per ray, unit geometric normal
    std::vector<std::int64_t> prim;   // input triangle id (of the cut solid, on a cap); -1 on a miss
    std::vector<float> u, v;
    std::vector<std::uint8_t> complete;
    FrameStats stats;
};
// With section planes, rays see only the kept side; a ray that enters a cut solid
// through a plane hits its cap: the point on the plane, the plane's normal.
LodRayHits intersect_lod(BlockCache& cache, CachedModel& model, const double* origins, const double* directions,
                         const double* tmin, const double* tmax, std::size_t n, unsigned threads,
                         const std::vector<SectionPlane>& sections = {});

// The cone slope of the solid-angle metric: a voxel of radius R at distance t subtends
// about pi R^2 / t^2, so R <= t * sqrt(omega / pi).
double solid_angle_cone(const RenderParams& params, double pixel_angle);

}  // namespace vastray
