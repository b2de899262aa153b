// The public side of rendering, built for the portable baseline: checks of cameras and
// parameters, and the entry points, which run the kernels of the active ISA (isa.h).
#include <cmath>
#include <cstdlib>
#include <stdexcept>
#include <string>
#include <string_view>

#include "vastray/kernels.h"
#include "vastray/lod_render.h"
#include "vastray/render.h"

namespace vastray {

void Camera::validate() const {
    if (!all_finite(eye) || !all_finite(target) || !all_finite(up) || !std::isfinite(fov_deg)) {
        throw std::invalid_argument("camera values must be finite numbers");
    }
    const Vec3d view = target - eye;
    if (!(dot(view, view) > 0)) throw std::invalid_argument("camera eye and target coincide (zero-length view direction)");
    if (!(dot(up, up) > 0)) throw std::invalid_argument("camera up vector has zero length");
    const Vec3d side = cross(normalize(view), normalize(up));
    if (!(length(side) > 1e-9)) throw std::invalid_argument("camera up vector is parallel to the view direction");
    if (!(fov_deg > 0 && fov_deg < 180)) throw std::invalid_argument("fov must be between 0 and 180 degrees (exclusive)");
    if (width <= 0 || height <= 0 || width > kMaxImageSide || height > kMaxImageSide) {
        throw std::invalid_argument("image size must be between 1x1 and " + std::to_string(kMaxImageSide) + "x" +
                                    std::to_string(kMaxImageSide));
    }
}

Shading parse_shading(const std::string& name) {
    if (name == "normal") return Shading::Normal;
    if (name == "headlight") return Shading::Headlight;
    if (name == "sun") return Shading::Sun;
    if (name == "ao") return Shading::AmbientOcclusion;
    if (name == "indirect") return Shading::Indirect;
    throw std::invalid_argument("unknown shading mode '" + name + "' (normal, headlight, sun, ao, indirect)");
}

const char* shading_name(Shading shading) {
    switch (shading) {
        case Shading::Normal: return "normal";
        case Shading::Headlight: return "headlight";
        case Shading::Sun: return "sun";
        case Shading::AmbientOcclusion: return "ao";
        case Shading::Indirect: return "indirect";
    }
    return "headlight";
}

bool traces_any_hit_rays(Shading shading) {
    return shading == Shading::Sun || shading == Shading::AmbientOcclusion || shading == Shading::Indirect;
}

bool closest_hits_walk_wide_bvh(const Scene& scene) {
    const char* env = std::getenv("VASTRAY_PRIMARY");
    const std::string_view choice = env != nullptr ? env : "";
    if (choice == "kd") return false;
    if (!choice.empty() && choice != "wide") {
        throw std::invalid_argument("VASTRAY_PRIMARY must be 'kd' or 'wide' (got '" + std::string(choice) + "')");
    }
    return scene.fits_wide_bvh();
}

bool any_hits_walk_wide_bvh(const Scene& scene) {
    const char* env = std::getenv("VASTRAY_ANYHIT");
    return !(env != nullptr && std::string_view(env) == "kd") && scene.fits_wide_bvh();
}

FrameStructures frame_structures(const Scene& scene, Shading shading) {
    FrameStructures s;
    s.primary_wide = closest_hits_walk_wide_bvh(scene);
    s.secondary = traces_any_hit_rays(shading);
    s.secondary_wide = s.secondary && any_hits_walk_wide_bvh(scene);
    return s;
}

void RenderParams::validate() const {
    if (!all_finite(sun_direction) || !(dot(sun_direction, sun_direction) > 0)) {
        throw std::invalid_argument("sun direction must be a finite non-zero vector");
    }
    if (ao_samples < 1 || ao_samples > 1024) throw std::invalid_argument("ao_samples must be in [1, 1024]");
    if (!std::isfinite(ao_distance) || ao_distance < 0) {
        throw std::invalid_argument("ao_distance must be a finite number >= 0 (0: a fifth of the model's diagonal)");
    }
    if (tile_size < 4 || tile_size > 1024) throw std::invalid_argument("tile_size must be in [4, 1024]");
    if (packets != 0 && packets != 1 && packets != 4 && packets != 16) {
        throw std::invalid_argument("packets must be 0 (the renderer's fastest), 1, 4 or 16");
    }
    if (!std::isfinite(pixels_of_error) || pixels_of_error < 0) {
        throw std::invalid_argument("pixels of error must be a finite number >= 0");
    }
    if (!std::isfinite(solid_angle) || solid_angle > 2 * 3.14159265358979323846) {
        throw std::invalid_argument("solid angle must be at most 2 pi steradians (negative: derived from PoE)");
    }
    if (sample_index < 0) throw std::invalid_argument("sample_index must be >= 0");
    if (request_limit < 0) throw std::invalid_argument("request_limit must be >= 0 (0: the cache's bound)");
    validate_sections(sections);
    validate_highlight(highlight);
}

void validate_highlight(const std::vector<TriangleRange>& ranges) {
    if (ranges.size() > kMaxHighlightRanges) {
        throw std::invalid_argument("at most " + std::to_string(kMaxHighlightRanges) + " highlight ranges");
    }
    for (std::size_t i = 0; i < ranges.size(); ++i) {
        if (ranges[i].first >= ranges[i].end) throw std::invalid_argument("a highlight range [first, end) must not be empty");
        if (i > 0 && ranges[i].first < ranges[i - 1].end) {
            throw std::invalid_argument("highlight ranges must be sorted and disjoint");
        }
    }
}

void validate_sections(const std::vector<SectionPlane>& planes) {
    if (planes.size() > kMaxSectionPlanes) {
        throw std::invalid_argument("at most " + std::to_string(kMaxSectionPlanes) + " section planes");
    }
    for (const SectionPlane& p : planes) {
        if (!all_finite(p.normal) || !(dot(p.normal, p.normal) > 0) || !std::isfinite(p.offset)) {
            throw std::invalid_argument("a section plane needs a finite non-zero normal and a finite offset");
        }
    }
}

double solid_angle_cone(const RenderParams& params, double pixel_angle) {
    if (params.solid_angle >= 0) return std::sqrt(params.solid_angle / 3.14159265358979323846);
    // Default: a cone twice the primary rays' (PoE pixels wide at unit distance). Wider
    // cones buy little speed and darken AO: near its origin a probe then meets voxels
    // whose boxes straddle the surface it leaves (bench/results/tradeoff-poe.md).
    return params.pixels_of_error * pixel_angle;
}

Frame render(const Scene& scene, const Camera& camera, const RenderParams& params) {
    return kernels().render_scene(scene, camera, params);
}

Frame render_lod(BlockCache& cache, CachedModel& model, const Camera& camera, const RenderParams& params) {
    return kernels().render_model(cache, model, camera, params);
}

LodRayHits intersect_lod(BlockCache& cache, CachedModel& model, const double* origins, const double* directions,
                         const double* tmin, const double* tmax, std::size_t n, unsigned threads,
                         const std::vector<SectionPlane>& sections) {
    validate_sections(sections);
    return kernels().intersect_model(cache, model, origins, directions, tmin, tmax, n, threads, sections);
}

BatchResult intersect_batch(const Scene& scene, const double* origins, const double* directions,
                            const double* tmin, const double* tmax, std::size_t n, unsigned threads,
                            const std::vector<SectionPlane>& sections) {
    validate_sections(sections);
    return kernels().intersect_scene(scene, origins, directions, tmin, tmax, n, threads, sections);
}

std::vector<std::uint8_t> occluded_batch(const Scene& scene, const double* origins, const double* directions,
                                         const double* tmin, const double* tmax, std::size_t n, unsigned threads) {
    return kernels().occluded_scene(scene, origins, directions, tmin, tmax, n, threads);
}

}  // namespace vastray
