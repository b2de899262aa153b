// What one frame (or one batch of rays) reports: ray and traversal counts for both
// renderers, and the block cache's view of the frame for the out-of-core one. One
// struct for both, bound once to Python (vastray.native.FrameStats), so the CLI, the
// server's wire schemas and the Python API name every field the same way.
#pragma once

#include <cstdint>

namespace vastray {

// Counters for one frame, filled by BlockCache::begin_frame/end_frame and the render
// threads. All zero for an in-core frame.
struct FrameCacheStats {
    std::uint32_t tick = 0;         // the frame's number (slot stamps use it)
    std::uint64_t requested = 0;    // distinct blocks this frame asked for
    std::uint64_t loaded = 0;       // blocks published at the start of this frame
    std::uint64_t evicted = 0;      // blocks evicted at the end of this frame
    std::uint64_t pending = 0;      // requests queued or loading after this frame
    std::uint64_t lookups = 0, lookup_hits = 0;
    std::uint64_t working_set_blocks = 0, working_set_bytes = 0;
    std::uint64_t bad_blocks = 0;   // lookups of blocks that failed to load
};

struct FrameStats {
    std::uint64_t primary_rays = 0, secondary_rays = 0;
    std::uint64_t node_visits = 0, triangle_tests = 0;
    std::uint64_t voxel_hits = 0;  // rays that ended on a LOD voxel (out of core only)
    // The frame's own time (in core, not the first-use builds of the structures its
    // rays walk, which the scene reports apart).
    double milliseconds = 0;
    unsigned threads = 0;
    FrameCacheStats cache;
    // Nothing was missing for this view at this accuracy. Always true in core; out of
    // core, false while blocks the view needs are still loading (or damaged).
    bool complete = true;
};

}  // namespace vastray
