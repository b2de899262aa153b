// The one frame loop of both renderers: tiles over the thread pool, primary rays in
// packets or singly, and the shading of every mode. A renderer supplies only its
// traversal, as a Backend:
//
//   using Ray = ...; using Hit = ...;   // Hit derives from vastray::Hit (t, prim, u, v)
//   using Lane = ...;                   // per-thread traversal state; has node_visits
//                                       // and triangle_tests counters
//   Ray primary_ray(int x, int y) const;
//   void trace(Lane&, const Ray&, Hit&) const;                       // closest hit
//   template <int Side> bool trace_packet(Lane&, const Ray*, Hit*) const;
//       // Side x Side rays in row order; false (nothing traced) when not coherent
//   std::int32_t prim_id(const Hit&) const;                          // what Frame::prim holds
//   void surface(const Hit&, Vec3f& unit_normal, Vec3f& colour) const;
//   bool occluded(Lane&, const Ray& primary, const Hit&, const Vec3f& n, const Vec3f& dir,
//                 float tmax, SecondaryRay kind) const;            // shadow and AO rays
//   float ao_distance() const;
//
// Both backends trace the same rays (CameraRays) and shade them with the same terms,
// so a full-detail out-of-core image equals the in-core one pixel for pixel.
#pragma once

#include <algorithm>
#include <chrono>
#include <vector>

#include "vastray/render.h"
#include "vastray/shading.h"

namespace vastray {

enum class SecondaryRay { Shadow, AmbientOcclusion };

// Rays traced by one lane; node and triangle counts live in the backend's lane.
struct LaneRays {
    std::uint64_t primary = 0, secondary = 0;
};

template <typename Backend>
class FrameShader {
public:
    using Ray = typename Backend::Ray;
    using Hit = typename Backend::Hit;
    using Lane = typename Backend::Lane;

    FrameShader(const Backend& backend, const RenderParams& params, int packets, Frame& frame)
        : backend_(backend), params_(params), packets_(packets), frame_(frame),
          sun_(Vec3f(normalize(params.sun_direction))) {}

    void render_tile(int x0, int y0, int x1, int y1, Lane& lane, LaneRays& rays) const {
        for (int y = y0; y < y1; y += 4) {
            for (int x = x0; x < x1; x += 4) {
                if (packets_ == 16 && x + 3 < x1 && y + 3 < y1 && trace_packet<4>(x, y, lane, rays)) continue;
                for (int qy = y; qy < std::min(y + 4, y1); qy += 2) {
                    for (int qx = x; qx < std::min(x + 4, x1); qx += 2) {
                        if (packets_ >= 4 && qx + 1 < x1 && qy + 1 < y1 && trace_packet<2>(qx, qy, lane, rays)) continue;
                        for (int py = qy; py < std::min(qy + 2, y1); ++py) {
                            for (int px = qx; px < std::min(qx + 2, x1); ++px) trace_single(px, py, lane, rays);
                        }
                    }
                }
            }
        }
    }

private:
    template <int Side>
    bool trace_packet(int x, int y, Lane& lane, LaneRays& rays) const {
        constexpr int N = Side * Side;
        Ray ray[N];
        Hit hit[N];
        for (int i = 0; i < N; ++i) ray[i] = backend_.primary_ray(x + i % Side, y + i / Side);
        if (!backend_.template trace_packet<Side>(lane, ray, hit)) return false;
        rays.primary += N;
        for (int i = 0; i < N; ++i) shade_pixel(x + i % Side, y + i / Side, ray[i], hit[i], lane, rays);
        return true;
    }

    void trace_single(int x, int y, Lane& lane, LaneRays& rays) const {
        const Ray ray = backend_.primary_ray(x, y);
        Hit hit;
        backend_.trace(lane, ray, hit);
        ++rays.primary;
        shade_pixel(x, y, ray, hit, lane, rays);
    }

    void shade_pixel(int x, int y, const Ray& ray, const Hit& hit, Lane& lane, LaneRays& rays) const {
        const std::size_t px = static_cast<std::size_t>(y) * frame_.width + x;
        std::uint8_t* rgb = frame_.rgb.data() + 3 * px;
        if (hit.prim == kNoHit) {
            shading::background(y, frame_.height, rgb);
            return;
        }
        frame_.depth[px] = hit.t;
        frame_.prim[px] = backend_.prim_id(hit);
        Vec3f n, colour;
        backend_.surface(hit, n, colour);
        if (params_.shading == Shading::Normal) {
            colour = (n + Vec3f(1, 1, 1)) * 0.5f;
        } else {
            const Vec3f dir = direction(ray);
            if (dot(n, dir) > 0) n = -n;  // shade the side the viewer sees
            colour = colour * light(ray, hit, n, dir, x, y, lane, rays);
        }
        shading::store_rgb(colour, rgb);
    }

    float light(const Ray& ray, const Hit& hit, const Vec3f& n, const Vec3f& dir, int x, int y, Lane& lane,
                LaneRays& rays) const {
        switch (params_.shading) {
            case Shading::Headlight:
                return shading::headlight(n, dir);
            case Shading::Sun: {
                const float lambert = dot(n, sun_);
                float visible = 0;
                if (lambert > 0) {
                    ++rays.secondary;
                    const float inf = std::numeric_limits<float>::infinity();
                    visible = backend_.occluded(lane, ray, hit, n, sun_, inf, SecondaryRay::Shadow) ? 0.0f : 1.0f;
                }
                return shading::sun(lambert, visible);
            }
            case Shading::AmbientOcclusion: {
                const int samples = std::max(1, params_.ao_samples);
                const shading::Basis basis(n);
                int open = 0;
                for (int k = 0; k < samples; ++k) {
                    ++rays.secondary;
                    const Vec3f probe = shading::ao_direction(basis, x, y, k);
                    if (!backend_.occluded(lane, ray, hit, n, probe, backend_.ao_distance(),
                                           SecondaryRay::AmbientOcclusion)) {
                        ++open;
                    }
                }
                return shading::ambient(open, samples);
            }
            case Shading::Normal:
                break;
        }
        return 1.0f;
    }

    static const Vec3f& direction(const vastray::Ray& r) { return r.dir; }
    template <typename R>
    static const Vec3f& direction(const R& r) {
        return r.ray.dir;
    }

    const Backend& backend_;
    const RenderParams& params_;
    int packets_;
    Frame& frame_;
    Vec3f sun_;
};

// Renders every tile of `frame` (already sized and blank) with `backend`, one Lane per
// pool lane, and adds the ray counts to frame.stats. `lanes` stays with the caller,
// which may have more to collect from it (the out-of-core renderer's block requests).
template <typename Backend>
void trace_frame(const Backend& backend, const Camera& camera, const RenderParams& params, int packets,
                 std::vector<typename Backend::Lane>& lanes, Frame& frame) {
    const FrameShader<Backend> shader(backend, params, packets, frame);
    std::vector<LaneRays> rays(lanes.size());
    shading::for_each_tile(camera, params, [&](int x0, int y0, int x1, int y1, unsigned lane) {
        shader.render_tile(x0, y0, x1, y1, lanes[lane], rays[lane]);
    });
    for (std::size_t i = 0; i < lanes.size(); ++i) {
        frame.stats.primary_rays += rays[i].primary;
        frame.stats.secondary_rays += rays[i].secondary;
        frame.stats.node_visits += lanes[i].node_visits;
        frame.stats.triangle_tests += lanes[i].triangle_tests;
    }
}

// Wall time of a frame, and the lanes it ran on, into its stats.
class FrameClock {
public:
    void stop(const RenderParams& params, FrameStats& stats) const {
        stats.threads = shading::lanes_used(params);
        stats.milliseconds = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start_).count();
    }

private:
    std::chrono::steady_clock::time_point start_ = std::chrono::steady_clock::now();
};

}  // namespace vastray
