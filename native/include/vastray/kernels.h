// The entry points each ISA build of the kernels provides (isa.h), and the table the
// public functions (render, render_lod, intersect_lod, intersect_batch, occluded_batch)
// dispatch through. Only types every path shares cross this boundary.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "vastray/isa.h"
#include "vastray/lod_render.h"
#include "vastray/render.h"
#include "vastray/scene.h"

namespace vastray {

struct KernelTable {
    Isa isa;
    Frame (*render_scene)(const Scene&, const Camera&, const RenderParams&);
    Frame (*render_model)(BlockCache&, CachedModel&, const Camera&, const RenderParams&);
    LodRayHits (*intersect_model)(BlockCache&, CachedModel&, const double* origins, const double* directions,
                                  const double* tmin, const double* tmax, std::size_t n, unsigned threads,
                                  const std::vector<SectionPlane>& sections);
    BatchResult (*intersect_scene)(const Scene&, const double* origins, const double* directions, const double* tmin,
                                   const double* tmax, std::size_t n, unsigned threads,
                                   const std::vector<SectionPlane>& sections);
    std::vector<std::uint8_t> (*occluded_scene)(const Scene&, const double* origins, const double* directions,
                                                const double* tmin, const double* tmax, std::size_t n,
                                                unsigned threads);
    void (*denoise_light)(float* light, const float* depth, const float* normal, int width, int height,
                          float pixel_angle, unsigned threads);
};

// One table per ISA build (kernels.cpp); the AVX ones exist only where the compiler
// builds them (VASTRAY_HAVE_AVX_KERNELS).
const KernelTable& kernel_table_sse2();
const KernelTable& kernel_table_avx();
const KernelTable& kernel_table_avx2();
const KernelTable& kernel_table_avx512();

// The table of the active ISA (active_isa()).
const KernelTable& kernels();

}  // namespace vastray

VASTRAY_KERNEL_BEGIN
// Defined once per ISA build, in that build's namespace.
Frame render_scene(const Scene& scene, const Camera& camera, const RenderParams& params);
Frame render_model(BlockCache& cache, CachedModel& model, const Camera& camera, const RenderParams& params);
LodRayHits intersect_model(BlockCache& cache, CachedModel& model, const double* origins, const double* directions,
                           const double* tmin, const double* tmax, std::size_t n, unsigned threads,
                           const std::vector<SectionPlane>& sections);
BatchResult intersect_scene(const Scene& scene, const double* origins, const double* directions, const double* tmin,
                            const double* tmax, std::size_t n, unsigned threads,
                            const std::vector<SectionPlane>& sections);
std::vector<std::uint8_t> occluded_scene(const Scene& scene, const double* origins, const double* directions,
                                         const double* tmin, const double* tmax, std::size_t n, unsigned threads);
// The indirect mode's edge-aware filter (denoise.h) on `light` (3 floats a pixel, in place),
// guided by depth (inf: no hit) and unit normals (3 floats a pixel): for tests.
void denoise_light(float* light, const float* depth, const float* normal, int width, int height, float pixel_angle,
                   unsigned threads);
VASTRAY_KERNEL_END
