#include "vastray/lod_render.h"

#include <chrono>
#include <cmath>
#include <stdexcept>

#include "vastray/lod_traverse_packet.h"
#include "vastray/shading.h"
#include "vastray/thread_pool.h"

namespace vastray {

double solid_angle_cone(const LodParams& lod, double pixel_angle) {
    if (lod.solid_angle >= 0) return std::sqrt(lod.solid_angle / 3.14159265358979323846);
    // Default: a cone twice the primary rays' (PoE pixels wide at unit distance). Wider
    // cones buy little speed and darken AO: near its origin a probe then meets voxels
    // whose boxes straddle the surface it leaves (bench/results/tradeoff-poe.md).
    return lod.pixels_of_error * pixel_angle;
}

namespace {

using namespace shading;
using lod_detail::load;

class LodFrameRenderer {
public:
    LodFrameRenderer(const ModelIndex& index, const Camera& cam, const RenderParams& params, const LodParams& lod,
                     Frame& frame)
        : index_(index), params_(params), frame_(frame), camera_(cam) {
        centre_ = index.centre();
        root_ = index.root_cell();
        const Vec3f diag = root_.hi - root_.lo;
        ao_distance_ = params.ao_distance > 0 ? static_cast<float>(params.ao_distance) : 0.2f * length(diag);
        sun_ = Vec3f(normalize(params.sun_direction));
        // Projected diameter 2R / (t * pixel_angle) <= PoE  <=>  R <= t * PoE * pixel_angle / 2.
        primary_cone_ = static_cast<float>(0.5 * lod.pixels_of_error * camera_.pixel_angle);
        ao_cone_ = static_cast<float>(solid_angle_cone(lod, camera_.pixel_angle));  // 0 at PoE 0
    }

    void render_tile(int x0, int y0, int x1, int y1, LodLane& lane, RenderStats& s) const {
        for (int y = y0; y < y1; y += 4) {
            for (int x = x0; x < x1; x += 4) {
                if (params_.packets == 16 && x + 3 < x1 && y + 3 < y1 && trace_packet<4>(x, y, lane, s)) continue;
                for (int qy = y; qy < std::min(y + 4, y1); qy += 2) {
                    for (int qx = x; qx < std::min(x + 4, x1); qx += 2) {
                        if (params_.packets == 4 && qx + 1 < x1 && qy + 1 < y1 && trace_packet<2>(qx, qy, lane, s)) continue;
                        for (int py = qy; py < std::min(qy + 2, y1); ++py) {
                            for (int px = qx; px < std::min(qx + 2, x1); ++px) {
                                const LodRay r = primary_ray(px, py);
                                LodHit hit;
                                lod_traverse<false>(lane, root_, r, hit);
                                ++s.primary_rays;
                                shade_pixel(px, py, r, hit, lane, s);
                            }
                        }
                    }
                }
            }
        }
    }

private:
    // A Side x Side pixel block as one packet, when its rays order every node alike.
    template <int Side>
    bool trace_packet(int x, int y, LodLane& lane, RenderStats& s) const {
        constexpr int N = Side * Side;
        LodRay rays[N];
        LodHit hits[N];
        for (int i = 0; i < N; ++i) rays[i] = primary_ray(x + i % Side, y + i / Side);
        if (!lod_packet_is_coherent<N>(rays)) return false;
        lod_traverse_packet<N>(lane, root_, rays, hits);
        s.primary_rays += N;
        for (int i = 0; i < N; ++i) shade_pixel(x + i % Side, y + i / Side, rays[i], hits[i], lane, s);
        return true;
    }

    LodRay primary_ray(int x, int y) const {
        LodRay r;
        // Local float frame: the centre is subtracted in double, as the in-core scene does.
        r.ray.org = Vec3f(camera_.eye - centre_);
        r.ray.dir = Vec3f(camera_.direction(x, y));
        r.cone = primary_cone_;
        return r;
    }

    void shade_pixel(int x, int y, const LodRay& r, const LodHit& hit, LodLane& lane, RenderStats& s) const {
        const std::size_t px = static_cast<std::size_t>(y) * frame_.width + x;
        std::uint8_t* rgb = frame_.rgb.data() + 3 * px;
        if (hit.prim == kNoHit) {
            background(y, frame_.height, rgb);
            return;
        }
        frame_.depth[px] = hit.t;
        frame_.prim[px] = hit.prim == kVoxelPrim ? -2 : static_cast<std::int32_t>(hit.prim);
        Vec3f n, colour;
        surface(hit, n, colour);
        if (params_.shading == Shading::Normal) {
            colour = (n + Vec3f(1, 1, 1)) * 0.5f;
        } else {
            if (dot(n, r.ray.dir) > 0) n = -n;  // shade the side the viewer sees
            colour = colour * shade(r, hit, n, x, y, lane, s);
        }
        store_rgb(colour, rgb);
    }

    // Normal (unit, unoriented) and base colour at a hit.
    void surface(const LodHit& hit, Vec3f& n, Vec3f& colour) const {
        if (hit.prim == kVoxelPrim) {
            format::unpack_sample(hit.sample, colour, n);
            if (!index_.has_colours()) colour = default_colour();
            return;
        }
        Vec3f v[3];
        triangle(hit, v);
        n = normalize(cross(v[1] - v[0], v[2] - v[0]));
        colour = default_colour();
        if (index_.has_colours()) {
            const auto l = layout(hit.tri_block);
            const std::uint32_t c = load<std::uint32_t>(hit.tri_block + l.colours + 4 * std::size_t{hit.local});
            colour = Vec3f(static_cast<float>(c & 0xffu), static_cast<float>((c >> 8) & 0xffu),
                           static_cast<float>((c >> 16) & 0xffu)) *
                     (1.0f / 255.0f);
        }
    }

    format::TriangleBlockLayout layout(const std::uint8_t* tb) const {
        return format::TriangleBlockLayout::of(load<std::uint32_t>(tb), load<std::uint32_t>(tb + 4),
                                               load<std::uint32_t>(tb + 8), index_.has_colours());
    }

    void triangle(const LodHit& hit, Vec3f* v) const {
        const auto l = layout(hit.tri_block);
        const std::uint8_t* corner = hit.tri_block + l.triangles + 6 * std::size_t{hit.local};
        for (int k = 0; k < 3; ++k) {
            const std::uint32_t i = load<std::uint16_t>(corner + 2 * k);
            v[k] = load<Vec3f>(hit.tri_block + l.vertices + 12 * std::size_t{i});
        }
    }

    // A secondary ray leaving a hit. LOD rays must clear the voxels of their own
    // surface: a triangle's ray skips what a cone of this footprint would accept around
    // its origin, a voxel's ray starts outside the voxel (offset grows with its size).
    LodRay spawn(const LodRay& primary, const LodHit& hit, const Vec3f& n, const Vec3f& dir, float cone,
                 float cone_t0) const {
        LodRay r;
        r.ray.dir = dir;
        r.cone = cone;
        r.cone_t0 = cone_t0;
        if (hit.prim == kVoxelPrim) {
            r.ray.org = primary.ray.org + primary.ray.dir * hit.t + n * (2.0f * hit.voxel_radius);
            r.ray.tmin = 0;
        } else {
            Vec3f v[3];
            triangle(hit, v);
            r.ray.org = offset_origin(v, hit, n);
            r.ray.tmin = 2.5f * cone_t0 * cone;
        }
        return r;
    }

    float shade(const LodRay& primary, const LodHit& hit, const Vec3f& n, int x, int y, LodLane& lane,
                RenderStats& s) const {
        const std::uint32_t skip = hit.prim == kVoxelPrim ? kNoHit : hit.prim;
        switch (params_.shading) {
            case Shading::Headlight:
                return headlight(n, primary.ray.dir);
            case Shading::Sun: {
                const float lambert = dot(n, sun_);
                float visible = 0;
                if (lambert > 0) {
                    // Shadow rays continue the primary ray's cone (PoE metric).
                    const LodRay shadow = spawn(primary, hit, n, sun_, primary_cone_, hit.t);
                    LodHit occluder;
                    ++s.secondary_rays;
                    visible = lod_traverse<true>(lane, root_, shadow, occluder, skip) ? 0.0f : 1.0f;
                }
                return sun(lambert, visible);
            }
            case Shading::AmbientOcclusion: {
                const int samples = std::max(1, params_.ao_samples);
                const Basis basis(n);
                int open = 0;
                for (int k = 0; k < samples; ++k) {
                    // AO rays start their own cone (solid-angle metric).
                    LodRay probe = spawn(primary, hit, n, ao_direction(basis, x, y, k), ao_cone_, 0.0f);
                    probe.ray.tmax = ao_distance_;
                    LodHit occluder;
                    ++s.secondary_rays;
                    if (!lod_traverse<true>(lane, root_, probe, occluder, skip)) ++open;
                }
                return ambient(open, samples);
            }
            case Shading::Normal:
                break;
        }
        return 1.0f;
    }

    const ModelIndex& index_;
    const RenderParams& params_;
    Frame& frame_;
    CameraRays camera_;
    Vec3d centre_;
    Box3f root_;
    float ao_distance_ = 1, primary_cone_ = 0, ao_cone_ = 0;
    Vec3f sun_;
};

}  // namespace

LodFrame render_lod(BlockCache& cache, CachedModel& model, const Camera& camera, const RenderParams& params,
                    const LodParams& lod) {
    validate(camera, params);
    if (!(lod.pixels_of_error >= 0) || !std::isfinite(lod.pixels_of_error)) {
        throw std::invalid_argument("pixels of error must be a finite number >= 0");
    }
    if (!std::isfinite(lod.solid_angle) || lod.solid_angle > 2 * 3.14159265358979323846) {
        throw std::invalid_argument("solid angle must be at most 2 pi steradians (negative: derived from PoE)");
    }
    const auto start = std::chrono::steady_clock::now();
    LodFrame out;
    Frame& frame = out.frame;
    blank_frame(frame, camera);

    const ModelIndex& index = model.index();
    const LodFrameRenderer renderer(index, camera, params, lod, frame);
    ThreadPool& pool = ThreadPool::global();
    std::vector<LodLane> lanes(pool.lanes());
    std::vector<RenderStats> stats(pool.lanes());
    const std::uint32_t tick = cache.begin_frame(out.cache);
    for (LodLane& lane : lanes) {
        lane.cache = &cache;
        lane.model = &model;
        lane.tick = tick;
        lane.level_first = index.level_first().data();
        lane.tri_level = static_cast<std::uint32_t>(index.level_count() - 1);
        lane.block_count = static_cast<std::uint32_t>(index.block_count());
        lane.has_colours = index.has_colours();
    }
    std::vector<std::pair<CachedModel*, std::uint32_t>> requests;
    try {
        for_each_tile(camera, params, [&](int x0, int y0, int x1, int y1, unsigned lane) {
            renderer.render_tile(x0, y0, x1, y1, lanes[lane], stats[lane]);
        });
    } catch (...) {
        // Close the frame (its requests reset the per-block counters) before passing on.
        for (const LodLane& lane : lanes) requests.insert(requests.end(), lane.requests.begin(), lane.requests.end());
        cache.end_frame(tick, requests, out.cache);
        throw;
    }
    std::uint64_t missing = 0;
    for (std::size_t i = 0; i < lanes.size(); ++i) {
        const LodLane& lane = lanes[i];
        requests.insert(requests.end(), lane.requests.begin(), lane.requests.end());
        frame.stats.primary_rays += stats[i].primary_rays;
        frame.stats.secondary_rays += stats[i].secondary_rays;
        frame.stats.node_visits += lane.node_visits;
        frame.stats.triangle_tests += lane.triangle_tests;
        out.voxel_hits += lane.voxel_hits;
        out.cache.lookups += lane.lookups;
        out.cache.lookup_hits += lane.hits;
        out.cache.working_set_blocks += lane.ws_blocks;
        out.cache.working_set_bytes += lane.ws_bytes;
        out.cache.bad_blocks += lane.bad;
        missing += lane.missing;
    }
    cache.end_frame(tick, requests, out.cache);
    out.complete = missing == 0;
    frame.stats.threads = lanes_used(params);
    frame.stats.milliseconds =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    return out;
}

}  // namespace vastray
