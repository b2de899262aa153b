#include "vastray/render.h"

#include <chrono>
#include <stdexcept>

#include "vastray/thread_pool.h"
#include "vastray/traverse_packet.h"

namespace vastray {

void Camera::validate() const {
    if (!all_finite(eye) || !all_finite(target) || !all_finite(up) || !std::isfinite(fov_deg)) {
        throw std::invalid_argument("camera values must be finite numbers");
    }
    const Vec3d view = target - eye;
    if (!(dot(view, view) > 0)) throw std::invalid_argument("camera eye and target coincide");
    if (!(dot(up, up) > 0)) throw std::invalid_argument("camera up vector has zero length");
    const Vec3d side = cross(normalize(view), normalize(up));
    if (!(length(side) > 1e-9)) throw std::invalid_argument("camera up vector is parallel to the view direction");
    if (!(fov_deg > 0 && fov_deg < 180)) throw std::invalid_argument("fov must be between 0 and 180 degrees (exclusive)");
    if (width <= 0 || height <= 0 || width > 16384 || height > 16384) {
        throw std::invalid_argument("image size must be between 1x1 and 16384x16384");
    }
}

Shading parse_shading(const std::string& name) {
    if (name == "normal") return Shading::Normal;
    if (name == "headlight") return Shading::Headlight;
    if (name == "sun") return Shading::Sun;
    if (name == "ao") return Shading::AmbientOcclusion;
    throw std::invalid_argument("unknown shading mode '" + name + "' (normal, headlight, sun, ao)");
}

namespace {

// PCG-style integer hash: deterministic per (pixel, sample) random numbers, so AO images
// are reproducible and independent of how tiles are scheduled over threads.
std::uint32_t hash32(std::uint32_t x) {
    x ^= x >> 16;
    x *= 0x7feb352du;
    x ^= x >> 15;
    x *= 0x846ca68bu;
    x ^= x >> 16;
    return x;
}
float unit_float(std::uint32_t h) { return static_cast<float>(h >> 8) * (1.0f / 16777216.0f); }

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

class FrameRenderer {
public:
    FrameRenderer(const Scene& scene, const Camera& cam, const RenderParams& params, Frame& frame)
        : scene_(scene), params_(params), frame_(frame) {
        const Vec3d w = normalize(cam.target - cam.eye);
        const Vec3d u = normalize(cross(w, cam.up));
        const Vec3d v = cross(u, w);
        const double tan_half = std::tan(cam.fov_deg * 0.5 * 3.14159265358979323846 / 180.0);
        const double aspect = static_cast<double>(cam.width) / cam.height;
        forward_ = w;
        right_ = u * (tan_half * aspect);
        upv_ = v * tan_half;
        eye_ = cam.eye;
        const Vec3d diag = scene.world_hi() - scene.world_lo();
        ao_distance_ = params.ao_distance > 0 ? static_cast<float>(params.ao_distance)
                                              : 0.2f * static_cast<float>(length(diag));
        sun_ = Vec3f(normalize(params.sun_direction));
    }

    void render_tile(int x0, int y0, int x1, int y1, TraversalCounters& c, RenderStats& s) const {
        for (int y = y0; y < y1; y += 4) {
            for (int x = x0; x < x1; x += 4) {
#if defined(VASTRAY_HAVE_PACKETS)
                if (params_.packets == 16 && x + 3 < x1 && y + 3 < y1 && trace_block(x, y, c, s)) continue;
#endif
                for (int qy = y; qy < std::min(y + 4, y1); qy += 2) {
                    for (int qx = x; qx < std::min(x + 4, x1); qx += 2) trace_quad(qx, qy, x1, y1, c, s);
                }
            }
        }
    }

private:
#if defined(VASTRAY_HAVE_PACKETS)
    // A 4x4 pixel block as one 16-ray packet (four SSE vectors, each a 2x2 quad).
    bool trace_block(int x, int y, TraversalCounters& c, RenderStats& s) const {
        Ray rays[16];
        Hit hits[16];
        int xs[16], ys[16];
        for (int q = 0; q < 4; ++q) {
            for (int k = 0; k < 4; ++k) {
                const int i = 4 * q + k;
                xs[i] = x + 2 * (q % 2) + k % 2;
                ys[i] = y + 2 * (q / 2) + k / 2;
                rays[i] = primary_ray(xs[i], ys[i]);
            }
        }
        if (!packet_is_coherent(rays, 16)) return false;
        traverse_packet<4>(scene_.tree(), scene_.tri_vertices(), rays, hits, c);
        for (int i = 0; i < 16; ++i) shade_pixel(xs[i], ys[i], rays[i], hits[i], c, s);
        s.primary_rays += 16;
        return true;
    }
#endif

    // A 2x2 quad as a 4-ray packet when it is whole and coherent, else single rays.
    void trace_quad(int x, int y, int x1, int y1, TraversalCounters& c, RenderStats& s) const {
        const int xs[4] = {x, x + 1, x, x + 1}, ys[4] = {y, y, y + 1, y + 1};
        Ray rays[4];
        Hit hits[4];
        const bool full_quad = x + 1 < x1 && y + 1 < y1;
        for (int k = 0; k < 4; ++k) {
            if (xs[k] < x1 && ys[k] < y1) rays[k] = primary_ray(xs[k], ys[k]);
        }
#if defined(VASTRAY_HAVE_PACKETS)
        if (full_quad && params_.packets >= 4 && packet_is_coherent(rays, 4)) {
            traverse_packet<1>(scene_.tree(), scene_.tri_vertices(), rays, hits, c);
            for (int k = 0; k < 4; ++k) shade_pixel(xs[k], ys[k], rays[k], hits[k], c, s);
            s.primary_rays += 4;
            return;
        }
#endif
        for (int k = 0; k < 4; ++k) {
            if (xs[k] >= x1 || ys[k] >= y1) continue;
            scene_.trace<false>(rays[k], hits[k], c);
            shade_pixel(xs[k], ys[k], rays[k], hits[k], c, s);
            ++s.primary_rays;
        }
    }

    Ray primary_ray(int x, int y) const {
        const double sx = 2.0 * (x + 0.5) / frame_.width - 1.0;
        const double sy = 1.0 - 2.0 * (y + 0.5) / frame_.height;
        WorldRay wr;
        wr.org = eye_;
        wr.dir = normalize(forward_ + right_ * sx + upv_ * sy);
        return scene_.to_local(wr);
    }

    void shade_pixel(int x, int y, const Ray& ray, const Hit& hit, TraversalCounters& c, RenderStats& s) const {
        const int height = frame_.height;
        const std::size_t px = static_cast<std::size_t>(y) * frame_.width + x;
        std::uint8_t* rgb = frame_.rgb.data() + 3 * px;
        if (hit.prim == kNoHit) {
            // Quiet vertical gradient: the model should stand out, not the background.
            const float g = static_cast<float>(y) / static_cast<float>(std::max(1, height - 1));
            rgb[0] = static_cast<std::uint8_t>(58 - 30 * g);
            rgb[1] = static_cast<std::uint8_t>(64 - 32 * g);
            rgb[2] = static_cast<std::uint8_t>(76 - 36 * g);
            return;
        }
        frame_.depth[px] = hit.t;
        frame_.prim[px] = static_cast<std::int32_t>(hit.prim);
        Vec3f n = normalize(scene_.normal(hit.prim));
        Vec3f colour = base_colour(hit.prim);
        if (params_.shading == Shading::Normal) {
            colour = (n + Vec3f(1, 1, 1)) * 0.5f;
        } else {
            if (dot(n, ray.dir) > 0) n = -n;  // shade the side the viewer sees
            colour = colour * shade(ray, hit, n, x, y, c, s);
        }
        for (int k = 0; k < 3; ++k) {
            rgb[k] = static_cast<std::uint8_t>(std::clamp(colour[k], 0.0f, 1.0f) * 255.0f + 0.5f);
        }
    }

    Vec3f base_colour(std::uint32_t prim) const {
        if (!scene_.has_colors()) return {0.78f, 0.78f, 0.76f};
        const std::uint8_t* c = scene_.color(prim);
        return Vec3f(c[0], c[1], c[2]) * (1.0f / 255.0f);
    }

    // Secondary rays start from the barycentric hit point (more accurate than o + t d)
    // pushed off the surface by a bound on its float error, and never report the
    // triangle they start on.
    Ray spawn(const Hit& hit, const Vec3f& n, const Vec3f& dir) const {
        const Vec3f* v = scene_.tri_vertices() + 3 * static_cast<std::size_t>(hit.prim);
        const Vec3f p = v[0] * (1.0f - hit.u - hit.v) + v[1] * hit.u + v[2] * hit.v;
        const float mag = std::max({std::abs(v[0].x), std::abs(v[0].y), std::abs(v[0].z),
                                    std::abs(v[1].x), std::abs(v[1].y), std::abs(v[1].z),
                                    std::abs(v[2].x), std::abs(v[2].y), std::abs(v[2].z)});
        const float offset = 32.0f * std::numeric_limits<float>::epsilon() * mag + 1e-30f;
        Ray r;
        r.org = p + n * offset;
        r.dir = dir;
        r.tmin = 0;
        return r;
    }

    float shade(const Ray& ray, const Hit& hit, const Vec3f& n, int x, int y, TraversalCounters& c,
                RenderStats& s) const {
        switch (params_.shading) {
            case Shading::Headlight:
                return 0.12f + 0.88f * std::abs(dot(n, ray.dir));
            case Shading::Sun: {
                const float lambert = dot(n, sun_);
                float visible = 0;
                if (lambert > 0) {
                    Ray shadow = spawn(hit, n, sun_);
                    Hit occluder;
                    ++s.secondary_rays;
                    visible = scene_.trace<true>(shadow, occluder, c, hit.prim) ? 0.0f : 1.0f;
                }
                return 0.18f + 0.82f * lambert * visible;
            }
            case Shading::AmbientOcclusion: {
                const int samples = std::max(1, params_.ao_samples);
                const Basis basis(n);
                int open = 0;
                const auto pixel_seed = static_cast<std::uint32_t>(y) * 0x9E3779B1u ^
                                        static_cast<std::uint32_t>(x) * 0x85EBCA77u;
                for (int k = 0; k < samples; ++k) {
                    const std::uint32_t h1 = hash32(pixel_seed ^ hash32(static_cast<std::uint32_t>(2 * k)));
                    const std::uint32_t h2 = hash32(pixel_seed ^ hash32(static_cast<std::uint32_t>(2 * k + 1)));
                    // Cosine-weighted hemisphere sample (Malley's method).
                    const float r = std::sqrt(unit_float(h1));
                    const float phi = 6.28318530718f * unit_float(h2);
                    const float lx = r * std::cos(phi), ly = r * std::sin(phi);
                    const float lz = std::sqrt(std::max(0.0f, 1.0f - lx * lx - ly * ly));
                    const Vec3f dir = basis.s * lx + basis.t * ly + basis.n * lz;
                    Ray probe = spawn(hit, n, dir);
                    probe.tmax = ao_distance_;
                    Hit occluder;
                    ++s.secondary_rays;
                    if (!scene_.trace<true>(probe, occluder, c, hit.prim)) ++open;
                }
                return 0.08f + 0.92f * static_cast<float>(open) / static_cast<float>(samples);
            }
            case Shading::Normal:
                break;
        }
        return 1.0f;
    }

    const Scene& scene_;
    const RenderParams& params_;
    Frame& frame_;
    Vec3d eye_, forward_, right_, upv_;
    float ao_distance_ = 1;
    Vec3f sun_;
};

}  // namespace

Frame render(const Scene& scene, const Camera& camera, const RenderParams& params) {
    camera.validate();
    if (!all_finite(params.sun_direction) || !(dot(params.sun_direction, params.sun_direction) > 0)) {
        throw std::invalid_argument("sun direction must be a finite non-zero vector");
    }
    if (params.ao_samples < 1 || params.ao_samples > 1024) throw std::invalid_argument("ao_samples must be in [1, 1024]");
    const auto start = std::chrono::steady_clock::now();
    Frame frame;
    frame.width = camera.width;
    frame.height = camera.height;
    const std::size_t pixels = static_cast<std::size_t>(camera.width) * camera.height;
    frame.rgb.assign(3 * pixels, 0);
    frame.depth.assign(pixels, std::numeric_limits<float>::infinity());
    frame.prim.assign(pixels, -1);

    const FrameRenderer renderer(scene, camera, params, frame);
    const int tile = std::max(4, params.tile_size);
    const int tiles_x = (camera.width + tile - 1) / tile, tiles_y = (camera.height + tile - 1) / tile;
    ThreadPool& pool = ThreadPool::global();
    std::vector<TraversalCounters> counters(pool.lanes());
    std::vector<RenderStats> stats(pool.lanes());
    pool.parallel_for(static_cast<std::size_t>(tiles_x) * tiles_y, [&](std::size_t t, unsigned lane) {
        const int tx = static_cast<int>(t % static_cast<std::size_t>(tiles_x));
        const int ty = static_cast<int>(t / static_cast<std::size_t>(tiles_x));
        const int x0 = tx * tile, y0 = ty * tile;
        renderer.render_tile(x0, y0, std::min(x0 + tile, camera.width), std::min(y0 + tile, camera.height),
                             counters[lane], stats[lane]);
    }, params.threads);

    for (std::size_t lane = 0; lane < stats.size(); ++lane) {
        frame.stats.primary_rays += stats[lane].primary_rays;
        frame.stats.secondary_rays += stats[lane].secondary_rays;
        frame.stats.node_visits += counters[lane].node_visits;
        frame.stats.triangle_tests += counters[lane].triangle_tests;
    }
    frame.stats.threads = params.threads == 0 ? pool.lanes() : std::min(params.threads, pool.lanes());
    frame.stats.milliseconds = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    return frame;
}

}  // namespace vastray
