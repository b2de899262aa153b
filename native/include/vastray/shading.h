// Pieces of the frame loop (frame_renderer.h) that both renderers' backends also use:
// the camera's primary rays, reproducible random numbers for AO, the hemisphere basis,
// the shading terms of each mode, the background, and the tile loop over the pool.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include <immintrin.h>

#include "vastray/isa.h"
#include "vastray/render.h"
#include "vastray/thread_pool.h"

VASTRAY_KERNEL_BEGIN
namespace shading {

// PCG-style integer hash: deterministic per (pixel, sample) random numbers, so AO images
// are reproducible and independent of how tiles are scheduled over threads.
inline std::uint32_t hash32(std::uint32_t x) {
    x ^= x >> 16;
    x *= 0x7feb352du;
    x ^= x >> 15;
    x *= 0x846ca68bu;
    x ^= x >> 16;
    return x;
}
inline float unit_float(std::uint32_t h) { return static_cast<float>(h >> 8) * (1.0f / 16777216.0f); }

struct Basis {
    Vec3f n, s, t;
    explicit Basis(const Vec3f& normal) : n(normal) {
        // Duff et al. 2017 branchless orthonormal basis.
        const float sign = std::copysign(1.0f, n.z);
        const float a = -1.0f / (sign + n.z);
        const float b = n.x * n.y * a;
        s = {1.0f + sign * n.x * n.x * a, sign * b, -sign * n.x};
        t = {b, sign + n.y * n.y * a, -n.y};
    }
};

// Cosine-weighted hemisphere direction (Malley's method) for sample k of a pixel: AO
// samples are k = 0, 1, ... (pass p of a still view starts at p * samples); diffuse
// rays of the indirect mode draw from another stream (salt).
inline Vec3f ao_direction(const Basis& basis, int x, int y, int k, std::uint32_t salt = 0) {
    const auto pixel_seed =
        (static_cast<std::uint32_t>(y) * 0x9E3779B1u ^ static_cast<std::uint32_t>(x) * 0x85EBCA77u) ^ salt;
    const std::uint32_t h1 = hash32(pixel_seed ^ hash32(static_cast<std::uint32_t>(2 * k)));
    const std::uint32_t h2 = hash32(pixel_seed ^ hash32(static_cast<std::uint32_t>(2 * k + 1)));
    const float r = std::sqrt(unit_float(h1));
    const float phi = 6.28318530718f * unit_float(h2);
    const float lx = r * std::cos(phi), ly = r * std::sin(phi);
    const float lz = std::sqrt(std::max(0.0f, 1.0f - lx * lx - ly * ly));
    return basis.s * lx + basis.t * ly + basis.n * lz;
}

// World-space primary rays of a pinhole or orthographic camera.
struct CameraRays {
    Vec3d eye, forward, right, up;
    int width = 1, height = 1;
    double pixel_angle = 0;  // width of a pixel at unit distance on the view axis
    // Orthographic: ray (x, y) leaves plane + ortho_right sx + ortho_up sy along forward;
    // ortho_right and ortho_up are the image's half extents at the target's distance.
    bool orthographic = false;
    double pixel_size = 0;  // orthographic: a pixel's width in world units
    Vec3d plane, ortho_right, ortho_up;

    explicit CameraRays(const Camera& cam) : width(cam.width), height(cam.height), orthographic(cam.orthographic) {
        const Vec3d w = normalize(cam.target - cam.eye);
        const Vec3d u = normalize(cross(w, cam.up));
        const Vec3d v = cross(u, w);
        const double tan_half = std::tan(cam.fov_deg * 0.5 * 3.14159265358979323846 / 180.0);
        const double aspect = static_cast<double>(cam.width) / cam.height;
        eye = cam.eye;
        forward = w;
        right = u * (tan_half * aspect);
        up = v * tan_half;
        pixel_angle = 2.0 * tan_half / cam.height;
        const double distance = length(cam.target - cam.eye);
        ortho_right = right * distance;
        ortho_up = up * distance;
        pixel_size = pixel_angle * distance;
        plane = eye;
    }

    // Orthographic rays start on the plane across the view through the eye, or behind it
    // far enough that every corner of the model's box [lo, hi] lies ahead, so the eye
    // cuts nothing off. The distance behind is rounded up to a power of two: renderers
    // whose boxes of one model differ in the last bits (the scene's, the file's root
    // cell) still trace the same rays.
    void start_behind(const Vec3d& lo, const Vec3d& hi) {
        if (!orthographic) return;
        double behind = 0;
        for (int k = 0; k < 8; ++k) {
            const Vec3d c((k & 1) ? hi.x : lo.x, (k & 2) ? hi.y : lo.y, (k & 4) ? hi.z : lo.z);
            behind = std::max(behind, dot(eye - c, forward));
        }
        if (behind > 0 && std::isfinite(behind)) plane = eye - forward * std::exp2(std::ceil(std::log2(behind)));
    }

    Vec3d origin(int x, int y) const {
        if (!orthographic) return eye;
        const double sx = 2.0 * (x + 0.5) / width - 1.0;
        const double sy = 1.0 - 2.0 * (y + 0.5) / height;
        return plane + ortho_right * sx + ortho_up * sy;
    }

    Vec3d direction(int x, int y) const {
        if (orthographic) return forward;
        const double sx = 2.0 * (x + 0.5) / width - 1.0;
        const double sy = 1.0 - 2.0 * (y + 0.5) / height;
        return normalize(forward + right * sx + up * sy);
    }

    // direction() of the pixels (x0 + k, y), k < 4, four lanes at a time: the same double
    // operations in the same order, so the same bits. Per pixel, direction() divides five
    // times and takes a square root, which the 4x4 packets' pixel blocks paid one pixel
    // after another (about 3 % of a 720p frame of the 10^8 plant at PoE 2).
    void directions4(int x0, int y, Vec3d out[4]) const {
        if (orthographic) {
            for (int k = 0; k < 4; ++k) out[k] = forward;
            return;
        }
#if VASTRAY_ISA_LEVEL >= VASTRAY_ISA_AVX
        typedef double lanes __attribute__((vector_size(32)));
        constexpr int W = 4;
#else
        typedef double lanes __attribute__((vector_size(16)));
        constexpr int W = 2;
#endif
        const double sy = 1.0 - 2.0 * (y + 0.5) / height;
        for (int h = 0; h < 4; h += W) {
            lanes px;
            for (int k = 0; k < W; ++k) px[k] = static_cast<double>(x0 + h + k);
            const lanes sx = 2.0 * (px + 0.5) / static_cast<double>(width) - 1.0;
            const lanes dx = forward.x + right.x * sx + up.x * sy;
            const lanes dy = forward.y + right.y * sx + up.y * sy;
            const lanes dz = forward.z + right.z * sx + up.z * sy;
            const lanes squared = dx * dx + dy * dy + dz * dz;
#if VASTRAY_ISA_LEVEL >= VASTRAY_ISA_AVX
            const lanes len = reinterpret_cast<lanes>(_mm256_sqrt_pd(reinterpret_cast<__m256d>(squared)));
#else
            const lanes len = reinterpret_cast<lanes>(_mm_sqrt_pd(reinterpret_cast<__m128d>(squared)));
#endif
            const lanes nx = dx / len, ny = dy / len, nz = dz / len;
            for (int k = 0; k < W; ++k) out[h + k] = Vec3d(nx[k], ny[k], nz[k]);
        }
    }
};

// Quiet vertical gradient: the model should stand out, not the background.
inline void background(int y, int height, std::uint8_t* rgb) {
    const float g = static_cast<float>(y) / static_cast<float>(std::max(1, height - 1));
    rgb[0] = static_cast<std::uint8_t>(58 - 30 * g);
    rgb[1] = static_cast<std::uint8_t>(64 - 32 * g);
    rgb[2] = static_cast<std::uint8_t>(76 - 36 * g);
}

inline void store_rgb(const Vec3f& colour, std::uint8_t* rgb) {
    for (int k = 0; k < 3; ++k) rgb[k] = static_cast<std::uint8_t>(std::clamp(colour[k], 0.0f, 1.0f) * 255.0f + 0.5f);
}

inline Vec3f default_colour() { return {0.78f, 0.78f, 0.76f}; }

inline float headlight(const Vec3f& n, const Vec3f& dir) { return 0.12f + 0.88f * std::abs(dot(n, dir)); }
inline float sun(float lambert, float visible) { return 0.18f + 0.82f * lambert * visible; }
inline float ambient(int open, int samples) {
    return 0.08f + 0.92f * static_cast<float>(open) / static_cast<float>(samples);
}

// The indirect mode's light, as multiples of a surface's albedo: a sun of radiance
// kSunLight (its irradiance over pi: what a white surface facing it reflects), and a sky
// of kSky over the upper hemisphere (around the camera's up vector), none from below.
// A diffuse ray that escapes brings the sky's radiance, one that hits a surface brings
// what that surface reflects of the sun (one bounce). Both are chosen so that a white
// surface lit by the sun under an open sky stays just below 1.
constexpr float kSunLight = 0.62f;
constexpr Vec3f kSky{0.36f, 0.39f, 0.44f};
constexpr int kDiffuseRays = 2;                 // per pixel and pass (paper 000 Table 5)
constexpr std::uint32_t kDiffuseSalt = 0x5bd1e995u;  // their random stream, apart from AO's
inline Vec3f sky(const Vec3f& dir, const Vec3f& up) { return dot(dir, up) > 0 ? kSky : Vec3f(0, 0, 0); }

// Where a secondary ray starts on a triangle: the barycentric point (more accurate than
// o + t d) pushed off the surface by a bound on its float error.
inline Vec3f offset_origin(const Vec3f* v, const Hit& hit, const Vec3f& n) {
    const Vec3f p = v[0] * (1.0f - hit.u - hit.v) + v[1] * hit.u + v[2] * hit.v;
    const float mag = std::max({std::abs(v[0].x), std::abs(v[0].y), std::abs(v[0].z), std::abs(v[1].x),
                                std::abs(v[1].y), std::abs(v[1].z), std::abs(v[2].x), std::abs(v[2].y),
                                std::abs(v[2].z)});
    const float offset = 32.0f * std::numeric_limits<float>::epsilon() * mag + 1e-30f;
    return p + n * offset;
}

// A frame of the camera's size: black, depth inf, prim -1 everywhere.
inline void blank_frame(Frame& frame, const Camera& camera, unsigned threads) {
    frame.width = camera.width;
    frame.height = camera.height;
    const std::size_t pixels = static_cast<std::size_t>(camera.width) * camera.height;
    frame.rgb.resize(3 * pixels);  // (uninitialised: written below, a band per lane)
    frame.depth.resize(pixels);
    frame.prim.resize(pixels);
    constexpr std::size_t kBand = 64 * 1024;  // pixels
    ThreadPool::global().parallel_for((pixels + kBand - 1) / kBand, [&](std::size_t band, unsigned) {
        const std::size_t p0 = band * kBand, p1 = std::min(pixels, p0 + kBand);
        std::fill(frame.rgb.begin() + 3 * p0, frame.rgb.begin() + 3 * p1, std::uint8_t{0});
        std::fill(frame.depth.begin() + p0, frame.depth.begin() + p1, std::numeric_limits<float>::infinity());
        std::fill(frame.prim.begin() + p0, frame.prim.begin() + p1, std::int32_t{-1});
    }, threads);
}

// Runs fn(x0, y0, x1, y1, lane) over the image's tiles on the global pool.
template <typename TileFn>
void for_each_tile(const Camera& camera, const RenderParams& params, TileFn&& fn) {
    const int tile = std::max(4, params.tile_size);
    const int tiles_x = (camera.width + tile - 1) / tile, tiles_y = (camera.height + tile - 1) / tile;
    ThreadPool::global().parallel_for(static_cast<std::size_t>(tiles_x) * tiles_y, [&](std::size_t t, unsigned lane) {
        const int x0 = static_cast<int>(t % static_cast<std::size_t>(tiles_x)) * tile;
        const int y0 = static_cast<int>(t / static_cast<std::size_t>(tiles_x)) * tile;
        fn(x0, y0, std::min(x0 + tile, camera.width), std::min(y0 + tile, camera.height), lane);
    }, params.threads);
}

inline unsigned lanes_used(const RenderParams& params) {
    const unsigned lanes = ThreadPool::global().lanes();
    return params.threads == 0 ? lanes : std::min(params.threads, lanes);
}

}  // namespace shading
VASTRAY_KERNEL_END
