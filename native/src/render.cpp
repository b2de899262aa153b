#include "vastray/render.h"

#include <chrono>
#include <stdexcept>

#include "vastray/shading.h"
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

using namespace shading;

class FrameRenderer {
public:
    FrameRenderer(const Scene& scene, const Camera& cam, const RenderParams& params, Frame& frame)
        : scene_(scene), params_(params), frame_(frame), camera_(cam) {
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
        WorldRay wr;
        wr.org = camera_.eye;
        wr.dir = camera_.direction(x, y);
        return scene_.to_local(wr);
    }

    void shade_pixel(int x, int y, const Ray& ray, const Hit& hit, TraversalCounters& c, RenderStats& s) const {
        const int height = frame_.height;
        const std::size_t px = static_cast<std::size_t>(y) * frame_.width + x;
        std::uint8_t* rgb = frame_.rgb.data() + 3 * px;
        if (hit.prim == kNoHit) {
            background(y, height, rgb);
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
        store_rgb(colour, rgb);
    }

    Vec3f base_colour(std::uint32_t prim) const {
        if (!scene_.has_colours()) return default_colour();
        const std::uint8_t* c = scene_.colour(prim);
        return Vec3f(c[0], c[1], c[2]) * (1.0f / 255.0f);
    }

    // Secondary rays never report the triangle they start on.
    Ray spawn(const Hit& hit, const Vec3f& n, const Vec3f& dir) const {
        Ray r;
        r.org = offset_origin(scene_.tri_vertices() + 3 * static_cast<std::size_t>(hit.prim), hit, n);
        r.dir = dir;
        r.tmin = 0;
        return r;
    }

    float shade(const Ray& ray, const Hit& hit, const Vec3f& n, int x, int y, TraversalCounters& c,
                RenderStats& s) const {
        switch (params_.shading) {
            case Shading::Headlight:
                return headlight(n, ray.dir);
            case Shading::Sun: {
                const float lambert = dot(n, sun_);
                float visible = 0;
                if (lambert > 0) {
                    Ray shadow = spawn(hit, n, sun_);
                    Hit occluder;
                    ++s.secondary_rays;
                    visible = scene_.trace<true>(shadow, occluder, c, hit.prim) ? 0.0f : 1.0f;
                }
                return sun(lambert, visible);
            }
            case Shading::AmbientOcclusion: {
                const int samples = std::max(1, params_.ao_samples);
                const Basis basis(n);
                int open = 0;
                for (int k = 0; k < samples; ++k) {
                    const Vec3f dir = ao_direction(basis, x, y, k);
                    Ray probe = spawn(hit, n, dir);
                    probe.tmax = ao_distance_;
                    Hit occluder;
                    ++s.secondary_rays;
                    if (!scene_.trace<true>(probe, occluder, c, hit.prim)) ++open;
                }
                return ambient(open, samples);
            }
            case Shading::Normal:
                break;
        }
        return 1.0f;
    }

    const Scene& scene_;
    const RenderParams& params_;
    Frame& frame_;
    CameraRays camera_;
    float ao_distance_ = 1;
    Vec3f sun_;
};

}  // namespace

Frame render(const Scene& scene, const Camera& camera, const RenderParams& params) {
    validate(camera, params);
    const auto start = std::chrono::steady_clock::now();
    Frame frame;
    blank_frame(frame, camera);
    const FrameRenderer renderer(scene, camera, params, frame);
    ThreadPool& pool = ThreadPool::global();
    std::vector<TraversalCounters> counters(pool.lanes());
    std::vector<RenderStats> stats(pool.lanes());
    for_each_tile(camera, params, [&](int x0, int y0, int x1, int y1, unsigned lane) {
        renderer.render_tile(x0, y0, x1, y1, counters[lane], stats[lane]);
    });

    for (std::size_t lane = 0; lane < stats.size(); ++lane) {
        frame.stats.primary_rays += stats[lane].primary_rays;
        frame.stats.secondary_rays += stats[lane].secondary_rays;
        frame.stats.node_visits += counters[lane].node_visits;
        frame.stats.triangle_tests += counters[lane].triangle_tests;
    }
    frame.stats.threads = lanes_used(params);
    frame.stats.milliseconds = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    return frame;
}

}  // namespace vastray
