// Pinhole camera, shading modes and the tiled frame renderer.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "vastray/scene.h"

namespace vastray {

struct Camera {
    Vec3d eye, target, up{0, 1, 0};
    double fov_deg = 45;  // vertical field of view
    int width = 640, height = 480;

    // Throws std::invalid_argument with a readable reason for absurd values
    // (NaN, eye == target, up parallel to the view, fov outside (0, 180), empty image).
    void validate() const;
};

enum class Shading { Normal, Headlight, Sun, AmbientOcclusion };
Shading parse_shading(const std::string& name);

struct RenderParams {
    Shading shading = Shading::Headlight;
    int ao_samples = 8;
    double ao_distance = 0;  // 0: a fifth of the model's diagonal
    Vec3d sun_direction{0.35, 0.8, 0.5};  // towards the sun, world frame
    unsigned threads = 0;                  // 0: every lane of the pool
    int tile_size = 16;
    // Primary rays per packet: 16 (4x4 blocks), 4 (2x2 quads) or 1 (single rays).
    int packets = 16;
};

struct RenderStats {
    std::uint64_t primary_rays = 0, secondary_rays = 0;
    std::uint64_t node_visits = 0, triangle_tests = 0;
    double milliseconds = 0;
    unsigned threads = 0;
};

struct Frame {
    int width = 0, height = 0;
    std::vector<std::uint8_t> rgb;     // height * width * 3
    std::vector<float> depth;          // distance along the unit view ray; inf on a miss
    std::vector<std::int32_t> prim;    // triangle id; -1 on a miss
    RenderStats stats;
};

Frame render(const Scene& scene, const Camera& camera, const RenderParams& params);

}  // namespace vastray
