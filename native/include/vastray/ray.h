// Rays and hits in a model's local float frame: the plain data every traversal (in
// core, out of core, each ISA path) and the scene's public API share. The code that
// traces them lives in the kernel headers (triangle.h, traverse*.h, lod_traverse*.h).
#pragma once

#include <cstdint>
#include <limits>

#include "vastray/vecmath.h"

namespace vastray {

constexpr std::uint32_t kNoHit = 0xffffffffu;

struct Ray {
    Vec3f org, dir;
    float tmin = 0, tmax = std::numeric_limits<float>::infinity();
};

struct Hit {
    float t = std::numeric_limits<float>::infinity();
    std::uint32_t prim = kNoHit;
    float u = 0, v = 0;  // barycentric weights of the second and third vertices
};

// Relative slack on split and box distances (8 float ulps): cheap insurance that
// traversal never skips a cell a ray touches, at the cost of rare extra visits.
constexpr float kSplitSlack = 8.0f * std::numeric_limits<float>::epsilon();

// One per thread, each on its own cache line: threads that bump neighbouring counters
// would pass the line back and forth on every ray (false sharing).
struct alignas(64) TraversalCounters {
    std::uint64_t node_visits = 0;
    std::uint64_t triangle_tests = 0;
};

}  // namespace vastray
