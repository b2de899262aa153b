#include "vastray/render.h"

#include <cmath>
#include <stdexcept>

#include "vastray/frame_renderer.h"
#include "vastray/traverse_packet.h"

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
    throw std::invalid_argument("unknown shading mode '" + name + "' (normal, headlight, sun, ao)");
}

const char* shading_name(Shading shading) {
    switch (shading) {
        case Shading::Normal: return "normal";
        case Shading::Headlight: return "headlight";
        case Shading::Sun: return "sun";
        case Shading::AmbientOcclusion: return "ao";
    }
    return "headlight";
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
}

namespace {

// The in-core scene as a frame-loop backend (frame_renderer.h).
class SceneBackend {
public:
    using Ray = vastray::Ray;
    using Hit = vastray::Hit;
    using Lane = TraversalCounters;

    SceneBackend(const Scene& scene, const Camera& camera, const RenderParams& params)
        : scene_(scene), camera_(camera) {
        const Vec3d diag = scene.world_hi() - scene.world_lo();
        ao_distance_ = params.ao_distance > 0 ? static_cast<float>(params.ao_distance)
                                              : 0.2f * static_cast<float>(length(diag));
    }

    Ray primary_ray(int x, int y) const {
        WorldRay wr;
        wr.org = camera_.eye;
        wr.dir = camera_.direction(x, y);
        return scene_.to_local(wr);
    }

    void trace(Lane& lane, const Ray& ray, Hit& hit) const { scene_.trace<false>(ray, hit, lane); }

    template <int Side>
    bool trace_packet(Lane& lane, const Ray* rays, Hit* hits) const {
#if defined(VASTRAY_HAVE_PACKETS)
        constexpr int N = Side * Side;
        if (!packet_is_coherent(rays, N)) return false;
        if constexpr (Side == 2) {
            traverse_packet<1>(scene_.tree(), scene_.tri_vertices(), rays, hits, lane);
        } else {
            // The SSE packet is four 2x2 quads, one per vector: regroup the rows.
            Ray quads[16];
            Hit quad_hits[16];
            for (int i = 0; i < 16; ++i) quads[i] = rays[quad_order(i)];
            traverse_packet<4>(scene_.tree(), scene_.tri_vertices(), quads, quad_hits, lane);
            for (int i = 0; i < 16; ++i) hits[quad_order(i)] = quad_hits[i];
        }
        return true;
#else
        (void)lane, (void)rays, (void)hits;
        return false;
#endif
    }

    std::int32_t prim_id(const Hit& hit) const { return static_cast<std::int32_t>(scene_.input_id(hit.prim)); }

    void surface(const Hit& hit, Vec3f& n, Vec3f& colour) const {
        n = normalize(scene_.normal(hit.prim));
        if (!scene_.has_colours()) {
            colour = shading::default_colour();
            return;
        }
        const std::uint8_t* c = scene_.colour(hit.prim);
        colour = Vec3f(c[0], c[1], c[2]) * (1.0f / 255.0f);
    }

    // Secondary rays start on the surface (offset by a bound on its float error) and
    // never report the triangle they start on.
    bool occluded(Lane& lane, const Ray&, const Hit& hit, const Vec3f& n, const Vec3f& dir, float tmax,
                  SecondaryRay) const {
        Ray r;
        r.org = shading::offset_origin(scene_.tri_vertices() + 3 * static_cast<std::size_t>(hit.prim), hit, n);
        r.dir = dir;
        r.tmin = 0;
        r.tmax = tmax;
        Hit occluder;
        return scene_.trace<true>(r, occluder, lane, hit.prim);
    }

    float ao_distance() const { return ao_distance_; }

private:
    // Row-order index of the i-th ray of the 16-ray packet's quad order.
    static int quad_order(int i) {
        const int q = i / 4, k = i % 4;
        return (2 * (q / 2) + k / 2) * 4 + 2 * (q % 2) + k % 2;
    }

    const Scene& scene_;
    shading::CameraRays camera_;
    float ao_distance_ = 1;
};

}  // namespace

Frame render(const Scene& scene, const Camera& camera, const RenderParams& params) {
    camera.validate();
    params.validate();
    const FrameClock clock;
    Frame frame;
    shading::blank_frame(frame, camera);
    const SceneBackend backend(scene, camera, params);
    std::vector<TraversalCounters> lanes(ThreadPool::global().lanes());
    trace_frame(backend, camera, params, params.packets_or(16), lanes, frame);
    clock.stop(params, frame.stats);
    return frame;
}

}  // namespace vastray
