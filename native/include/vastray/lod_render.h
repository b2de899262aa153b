// Frames of a built model rendered from the block cache with level of detail.
#pragma once

#include <memory>

#include "vastray/block_cache.h"
#include "vastray/render.h"

namespace vastray {

struct LodParams {
    // Pixels of error: a voxel may stand in for its subtree once its projected diameter
    // is at most this many pixels. 0 renders full detail (never stops at a voxel).
    double pixels_of_error = 2;
    // Solid-angle metric for AO rays: the largest solid angle (steradians) a voxel may
    // subtend from an AO ray's origin. Negative: derived from pixels_of_error.
    double solid_angle = -1;
};

struct LodFrame {
    Frame frame;  // frame.prim: input triangle id, -1 for background, -2 for a voxel
    FrameCacheStats cache;
    std::uint64_t voxel_hits = 0;
    bool complete = false;  // nothing was missing for this view at this accuracy
};

LodFrame render_lod(BlockCache& cache, CachedModel& model, const Camera& camera, const RenderParams& params,
                    const LodParams& lod);

// The cone slope of the solid-angle metric: a voxel of radius R at distance t subtends
// about pi R^2 / t^2, so R <= t * sqrt(omega / pi).
double solid_angle_cone(const LodParams& lod, double pixel_angle);

}  // namespace vastray
