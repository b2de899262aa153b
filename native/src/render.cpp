// The in-core renderer and batch queries, one build per ISA (isa.h): a Scene as a
// frame-loop backend (frame_renderer.h), and closest/any-hit queries of world rays.
#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "vastray/frame_renderer.h"
#include "vastray/interleave.h"
#include "vastray/kernels.h"
#include "vastray/thread_pool.h"
#include "vastray/traverse_packet.h"
#include "vastray/wide_traverse.h"
#include "vastray/wide_traverse_packet.h"

VASTRAY_KERNEL_BEGIN

namespace {

// Primary packets in flight on a large tree: the renderer takes them in groups of up to 16
// packets (a 16x16 tile), 8 in flight: 10^7 plant 4x4-packet frames 1.28x one packet at a
// time in two series (4 in flight from groups of 4: 1.19-1.24x; 6 from 16: 1.24-1.27x; 8
// from 8: 1.28x).
constexpr int kPacketsInFlight = 8;

// Closest hits of `count` coherent packets of N rays (rays[j], hits[j]): several in flight
// on a large tree (`interleave`), else one after the other; the same answers either way.
template <int N>
void trace_coherent_packets(const Scene& scene, bool interleave, const Ray* const* rays, Hit* const* hits, int count,
                            TraversalCounters& counters) {
    if (interleave) {
        traverse_packets<N, kPacketsInFlight>(scene.tree(), scene.tri_vertices(), rays, hits, count, counters);
        return;
    }
    for (int j = 0; j < count; ++j) traverse_packet<N>(scene.tree(), scene.tri_vertices(), rays[j], hits[j], counters);
}

// AO packets in flight on a large tree: 8 measured 1.32x one at a time, 4 1.27x (10^7 plant).
constexpr int kOcclusionInFlight = 8;

// Walks of the wide BVH in flight on a large tree (interleave.h), any-hit and closest-hit
// (the diffuse rays: 1.04-1.10x one at a time on 10^7 indirect frames). On the 10^7
// plant's AO rays (a 650 MB tree) 8 ran 1.22x one at a time and 4 1.07x; at 10^6 (63 MB)
// 8 ran 0.98x, at 10^5 0.85x. With the 4-triangle leaves 16 ran 1.09x of 8 (AO and
// shadow rays, 12 between them; frames 1.00-1.14x; docs/native-core.md, "The wide BVH
// for secondary rays").
constexpr int kWideInFlight = 16;
// Primary packets through the wide BVH in flight on a large tree: 8 ran 1.13x (plant) and
// 1.28x (mandelbulb) one at a time at 10^7, 4 as 8 (AMD EPYC; docs/native-core.md).
constexpr int kWidePacketsInFlight = 8;

// Any hits of `count` rays through the wide BVH (occluded_wide_in_flight's ray_of and
// answer): kWideInFlight walks in flight on a large tree, else one after the other.
template <typename RayOf, typename Answer>
void occluded_wide_rays(const WideBvh& bvh, bool interleave, std::size_t count, RayOf&& ray_of, Answer&& answer,
                        TraversalCounters& counters) {
    if (interleave) {
        occluded_wide_in_flight<kWideInFlight>(bvh, count, ray_of, answer, counters);
        return;
    }
    for (std::size_t i = 0; i < count; ++i) {
        Ray ray;
        std::uint32_t skip = kNoHit;
        if (ray_of(i, ray, skip) && occluded_wide(bvh, ray, counters, skip)) answer(i);
    }
}

// Closest hits of `count` rays through the wide BVH (closest_wide_in_flight's ray_of and
// hit_of), as occluded_wide_rays goes: in flight on a large tree, else one after the other.
template <typename RayOf, typename HitOf>
void closest_wide_rays(const WideBvh& bvh, bool interleave, std::size_t count, RayOf&& ray_of, HitOf&& hit_of,
                       TraversalCounters& counters) {
    if (interleave) {
        closest_wide_in_flight<kWideInFlight>(bvh, count, ray_of, hit_of, counters);
        return;
    }
    for (std::size_t i = 0; i < count; ++i) {
        Ray ray;
        std::uint32_t skip = kNoHit;
        if (ray_of(i, ray, skip)) closest_wide(bvh, ray, hit_of(i), counters, skip);
    }
}

// The structure secondary rays walk (any-hit rays, and the indirect mode's diffuse rays):
// the scene's wide BVH, or null for the kd-tree (any_hits_walk_wide_bvh).
const WideBvh* any_hit_bvh(const Scene& scene) {
    return any_hits_walk_wide_bvh(scene) ? scene.wide_bvh() : nullptr;
}

// The structure closest-hit rays walk (the renderer's primary rays, the batch query): the
// scene's wide BVH (its packets beat the kd-tree's by 1.21-1.66x, docs/native-core.md),
// or null for the kd-tree (closest_hits_walk_wide_bvh; VASTRAY_PRIMARY=kd gives the walk
// the out-of-core renderer shares, whose full-detail frames equal it bit for bit).
const WideBvh* primary_bvh(const Scene& scene) {
    return closest_hits_walk_wide_bvh(scene) ? scene.wide_bvh() : nullptr;
}

// The closest hit of one ray through the wide BVH, or the kd-tree where `bvh` is null;
// true on a hit.
bool closest_ray(const Scene& scene, const WideBvh* bvh, const Ray& ray, Hit& hit, TraversalCounters& counters) {
    if (bvh == nullptr) return traverse<false>(scene.tree(), scene.tri_vertices(), ray, hit, counters);
    closest_wide(*bvh, ray, hit, counters);
    return hit.prim != kNoHit;
}

// Closest hits of `count` coherent packets of N rays (rays[j], hits[j]) through the wide
// BVH, or the kd-tree's packets where `bvh` is null; several in flight where `interleave`
// says the structure walked is large.
template <int N>
void closest_packets(const Scene& scene, const WideBvh* bvh, bool interleave, const Ray* const* rays,
                     Hit* const* hits, int count, TraversalCounters& counters) {
    if (bvh == nullptr) {
        trace_coherent_packets<N>(scene, interleave, rays, hits, count, counters);
    } else if (interleave) {
        closest_wide_packets<N, kWidePacketsInFlight>(*bvh, rays, hits, count, counters);
    } else {
        closest_wide_packets<N, 1>(*bvh, rays, hits, count, counters);
    }
}

// A secondary ray of the in-core scene: never reports the triangle it starts on.
struct SceneSecondary {
    Ray ray;
    std::uint32_t skip = kNoHit;
};

// Any hits of N rays in lane order (N = 1: traverse(), else a packet), the lanes outside
// `mask` holding copies of a live ray; skip[i] is the triangle lane i starts on (null:
// none). Shared by the renderer (scene_occluded) and the batch query.
template <int N>
std::uint32_t occluded_rays(const Scene& scene, const Ray* rays, const std::uint32_t* skip, std::uint32_t mask,
                            TraversalCounters& counters) {
    if constexpr (N == 1) {
        Hit occluder;
        return (mask & 1u) && traverse<true>(scene.tree(), scene.tri_vertices(), rays[0], occluder, counters,
                                              skip != nullptr ? skip[0] : kNoHit)
                   ? 1u
                   : 0u;
    } else {
        return occluded_packet<N>(scene.tree(), scene.tri_vertices(), rays, skip, mask, counters);
    }
}

// N secondary rays gathered into lane order (rays r, skip ids) for a packet; lanes
// outside `mask` copy a live ray (with no live ray, lane 0's).
template <int N>
void to_lanes(const SceneSecondary* rays, std::uint32_t mask, Ray* r, std::uint32_t* skip) {
    const int any = mask ? __builtin_ctz(mask) : 0;
    for (int i = 0; i < N; ++i) {
        const SceneSecondary& s = rays[(mask >> i & 1u) ? i : any];
        r[i] = s.ray;
        skip[i] = s.skip;
    }
}

// The renderer's secondary rays, gathered into lane order for occluded_rays.
template <int N>
std::uint32_t scene_occluded(const Scene& scene, const SceneSecondary* rays, std::uint32_t mask,
                             TraversalCounters& counters) {
    if constexpr (N == 1) {
        return occluded_rays<1>(scene, &rays[0].ray, &rays[0].skip, mask, counters);
    } else {
        Ray r[N];
        std::uint32_t skip[N];
        to_lanes<N>(rays, mask, r, skip);
        return occluded_rays<N>(scene, r, skip, mask, counters);
    }
}

// The in-core scene as a frame-loop backend (frame_renderer.h).
class SceneBackend {
public:
    using Ray = vastray::Ray;
    using Hit = vastray::Hit;
    using Lane = TraversalCounters;
    using Secondary = SceneSecondary;

    SceneBackend(const Scene& scene, const Camera& camera, const RenderParams& params)
        : SceneBackend(scene, camera, params, frame_structures(scene, params.shading)) {}

    // (The structures are built here, before the frame's parallel loop: the builds run on
    // the pool too. The kd-tree only where some ray of the frame walks it.)
    SceneBackend(const Scene& scene, const Camera& camera, const RenderParams& params, const FrameStructures& walked)
        : scene_(scene),
          camera_(camera),
          wide_(walked.secondary && walked.secondary_wide ? scene.wide_bvh() : nullptr),
          wide_interleave_(wide_ != nullptr && interleaves(wide_->memory_bytes())),
          primary_(walked.primary_wide ? scene.wide_bvh() : nullptr),
          primary_interleave_(primary_ != nullptr && interleaves(primary_->memory_bytes())),
          kd_(walked.kd() ? &scene.tree() : nullptr),
          interleave_(kd_ != nullptr && interleaves(kd_->memory_bytes())) {
        const Vec3d diag = scene.world_hi() - scene.world_lo();
        ao_distance_ = params.ao_distance > 0 ? static_cast<float>(params.ao_distance)
                                              : 0.2f * static_cast<float>(length(diag));
        camera_.start_behind(scene.world_lo(), scene.world_hi());
    }

    Ray primary_ray(int x, int y) const { return primary_from(camera_.origin(x, y), camera_.direction(x, y)); }
    Box3f bounds() const { return scene_.bounds(); }
    void primary_rays4(int x0, int y, Ray* out) const {
        if (camera_.orthographic) {
            for (int k = 0; k < 4; ++k) out[k] = primary_ray(x0 + k, y);
            return;
        }
        Vec3d dirs[4];
        camera_.directions4(x0, y, dirs);
        for (int k = 0; k < 4; ++k) out[k] = primary_along(dirs[k]);
    }

    void trace(Lane& lane, const Ray& ray, Hit& hit) const { closest_ray(scene_, primary_, ray, hit, lane); }
    void trace_stream(Lane& lane, const Ray* rays, Hit* hits, int n) const {
        if (primary_ == nullptr) {
            for (int i = 0; i < n; ++i) trace(lane, rays[i], hits[i]);
            return;
        }
        closest_wide_rays(
            *primary_, primary_interleave_, static_cast<std::size_t>(n),
            [&](std::size_t i, Ray& ray, std::uint32_t&) {
                ray = rays[i];
                return true;
            },
            [&](std::size_t i) -> Hit& { return hits[i]; }, lane);
    }

    template <int Side>
    bool trace_packet(Lane& lane, const Ray* rays, Hit* hits) const {
        constexpr int N = Side * Side;
        if (!packet_is_coherent(rays, N)) return false;
        closest_packets<N>(scene_, primary_, false, &rays, &hits, 1, lane);
        return true;
    }

    // (The frame loop hands over at most kMaxGroup packets at a time.)
    template <int Side>
    void trace_packets(Lane& lane, const Ray* const* rays, Hit* const* hits, bool* traced, int count) const {
        constexpr int N = Side * Side;
        const Ray* coherent[kMaxGroup];
        Hit* out[kMaxGroup];
        int m = 0;
        for (int j = 0; j < count; ++j) {
            traced[j] = j < kMaxGroup && packet_is_coherent(rays[j], N);
            if (traced[j]) {
                coherent[m] = rays[j];
                out[m++] = hits[j];
            }
        }
        closest_packets<N>(scene_, primary_, primary_ != nullptr ? primary_interleave_ : interleave_, coherent, out, m,
                           lane);
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
    Secondary secondary_ray(const Ray&, const Hit& hit, const Vec3f& n, const Vec3f& dir, float tmax,
                            SecondaryRay) const {
        Secondary s;
        s.ray.org = shading::offset_origin(scene_.tri_vertices() + 3 * static_cast<std::size_t>(hit.prim), hit, n);
        s.ray.dir = dir;
        s.ray.tmin = 0;
        s.ray.tmax = tmax;
        s.skip = hit.prim;
        return s;
    }

    template <int N>
    std::uint32_t occluded(Lane& lane, const Secondary* rays, std::uint32_t mask, RayGroup group) const {
        if (wide_ != nullptr) {
            std::uint32_t blocked = 0;
            occluded_group<N>(lane, &rays, &mask, &blocked, 1, group);
            return blocked;
        }
        return scene_occluded<N>(scene_, rays, mask, lane);
    }

    // Several occlusion queries: on a large tree their packets go several in flight, as
    // the batch query's do (occluded_packets), else one after the other.
    template <int N>
    void occluded_group(Lane& lane, const Secondary* const* rays, const std::uint32_t* mask, std::uint32_t* blocked,
                        int count, RayGroup group) const {
        if (wide_ != nullptr) {
            // Every live lane of every query is its own walk (wide nodes have no packets).
            for (int j = 0; j < count; ++j) blocked[j] = 0;
            occluded_wide_rays(
                *wide_, wide_interleave_, static_cast<std::size_t>(count) * N,
                [&](std::size_t i, Ray& ray, std::uint32_t& skip) {
                    const std::size_t j = i / N, k = i % N;
                    if (!(mask[j] >> k & 1u)) return false;
                    ray = rays[j][k].ray;
                    skip = rays[j][k].skip;
                    return true;
                },
                [&](std::size_t i) { blocked[i / N] |= 1u << (i % N); }, lane);
            return;
        }
        if constexpr (N > 1) {
            if (interleave_) {
                for (int j0 = 0; j0 < count; j0 += kMaxGroup) {
                    const int m = std::min(kMaxGroup, count - j0);
                    Ray r[kMaxGroup][N];
                    std::uint32_t skip[kMaxGroup][N];
                    const Ray* r_of[kMaxGroup];
                    const std::uint32_t* skip_of[kMaxGroup];
                    for (int j = 0; j < m; ++j) {
                        // (A query with no live ray has no packet: its walk never starts.)
                        to_lanes<N>(rays[j0 + j], mask[j0 + j], r[j], skip[j]);
                        r_of[j] = r[j];
                        skip_of[j] = skip[j];
                    }
                    occluded_packets<N, kOcclusionInFlight>(*kd_, scene_.tri_vertices(), r_of, skip_of,
                                                           mask + j0, blocked + j0, m, lane);
                }
                return;
            }
        }
        for (int j = 0; j < count; ++j) blocked[j] = mask[j] ? occluded<N>(lane, rays[j], mask[j], group) : 0u;
    }

    // Closest hits of the rays in `mask` (the indirect mode's diffuse rays): through the wide
    // BVH where the frame's any-hit rays walk it (walks in flight on a large tree), else one
    // after the other on the kd-tree. Against the kd-tree's walks the wide ones made indirect
    // frames 1.49-1.80x faster, with the same images (docs/native-core.md, "The wide BVH for
    // secondary rays").
    template <int N>
    void trace_secondary(Lane& lane, const Secondary* rays, Hit* hits, std::uint32_t mask) const {
        if (wide_ != nullptr) {
            closest_wide_rays(
                *wide_, wide_interleave_, N,
                [&](std::size_t i, Ray& ray, std::uint32_t& skip) {
                    if (!(mask >> i & 1u)) return false;
                    ray = rays[i].ray;
                    skip = rays[i].skip;
                    return true;
                },
                [&](std::size_t i) -> Hit& { return hits[i]; }, lane);
            return;
        }
        for (; mask; mask &= mask - 1) {
            const int i = __builtin_ctz(mask);
            traverse<false>(*kd_, scene_.tri_vertices(), rays[i].ray, hits[i], lane, rays[i].skip);
        }
    }

    float ao_distance() const { return ao_distance_; }
    Vec3d centre() const { return scene_.centre(); }

private:
    static constexpr int kMaxGroup = 16;

    // The primary ray from the eye along world direction `dir`, in the scene's frame.
    Ray primary_along(const Vec3d& dir) const { return primary_from(camera_.eye, dir); }
    Ray primary_from(const Vec3d& org, const Vec3d& dir) const {
        WorldRay wr;
        wr.org = org;
        wr.dir = dir;
        return scene_.to_local(wr);
    }

    const Scene& scene_;
    shading::CameraRays camera_;
    const WideBvh* wide_;  // null: secondary rays walk the kd-tree
    bool wide_interleave_;
    const WideBvh* primary_;  // null: primary rays walk the kd-tree
    bool primary_interleave_;
    const KdTree* kd_;  // null where no ray of the frame walks the kd-tree
    bool interleave_;
    float ao_distance_ = 1;
};

WorldRay load_ray(const double* origins, const double* directions, const double* tmin, const double* tmax,
                  std::size_t i) {
    WorldRay r;
    r.org = {origins[3 * i], origins[3 * i + 1], origins[3 * i + 2]};
    r.dir = {directions[3 * i], directions[3 * i + 1], directions[3 * i + 2]};
    r.tmin = tmin[i];
    r.tmax = tmax[i];
    return r;
}

bool ray_is_valid(const WorldRay& r) {
    return all_finite(r.org) && all_finite(r.dir) && dot(r.dir, r.dir) > 0 && !std::isnan(r.tmin) &&
           !std::isnan(r.tmax);
}

constexpr std::size_t kBatch = 1024;

// Whether rays i and j of a batch have the same origin (or direction): `v` holds them.
bool same_vector(const double* v, std::size_t i, std::size_t j) {
    return v[3 * i] == v[3 * j] && v[3 * i + 1] == v[3 * j + 1] && v[3 * i + 2] == v[3 * j + 2];
}

}  // namespace

void denoise_light(float* light, const float* depth, const float* normal, int width, int height, float pixel_angle,
                   unsigned threads) {
    denoise::Guides guides;
    guides.width = width;
    guides.height = height;
    guides.depth = depth;
    guides.normal = normal;
    guides.pixel_angle = pixel_angle;
    const std::size_t size = 3 * static_cast<std::size_t>(width) * static_cast<std::size_t>(height);
    std::vector<float> values(light, light + size);
    denoise::filter(guides, values, threads);
    std::copy(values.begin(), values.end(), light);
}

Frame render_scene(const Scene& scene, const Camera& camera, const RenderParams& params) {
    camera.validate();
    params.validate();
    // The structures the frame's rays walk are built on their first use, here, before the
    // clock starts: a frame's time is the frame's alone (Scene.any_hit_stats() and
    // Scene.build_stats report the builds' own times).
    const SceneBackend backend(scene, camera, params);
    const FrameClock clock;
    Frame frame;
    shading::blank_frame(frame, camera, params.threads);
    std::vector<TraversalCounters> lanes(ThreadPool::global().lanes());
    trace_frame(backend, camera, params, params.packets_or(16), lanes, frame);
    clock.stop(params, frame.stats);
    return frame;
}

BatchResult intersect_scene(const Scene& scene, const double* origins, const double* directions, const double* tmin,
                            const double* tmax, std::size_t n, unsigned threads,
                            const std::vector<SectionPlane>& planes) {
    const LocalSections sections(planes, scene.centre());
    BatchResult out;
    out.t.assign(n, std::numeric_limits<double>::infinity());
    out.prim.assign(n, -1);
    out.u.assign(n, 0.0f);
    out.v.assign(n, 0.0f);
    out.normal.assign(3 * n, 0.0f);
    ThreadPool& pool = ThreadPool::global();
    std::vector<TraversalCounters> lane_counters(pool.lanes());
    // Runs of 16 rays from one origin whose directions share their signs (a row of camera
    // rays) go as packets, several in flight on a large tree, as the renderer's do, through
    // the structure the renderer's primary rays walk (primary_bvh): the same answers as one
    // ray at a time, and as the frame's. Other rays, and every ray when section planes cut
    // the scene, go one at a time.
    constexpr int kPacket = 16;
    // (The wide BVH is built here, before the parallel loop: the build runs on the pool.)
    const WideBvh* bvh = primary_bvh(scene);
    const bool interleave = interleaves(bvh != nullptr ? bvh->memory_bytes() : scene.tree().memory_bytes());
    pool.parallel_for((n + kBatch - 1) / kBatch, [&](std::size_t b, unsigned lane) {
        TraversalCounters& c = lane_counters[lane];
        const std::size_t begin = b * kBatch, end = std::min(n, (b + 1) * kBatch);
        auto store = [&](std::size_t i, const Hit& hit, const Ray& ray, int entered) {
            Vec3f nrm = normalize(scene.normal(hit.prim));
            double t = hit.t;
            if (entered >= 0 && dot(nrm, ray.dir) > 0) {
                // In a cut solid: its cap, on the plane.
                t = ray.tmin;
                nrm = -sections.normal(entered);
            }
            out.t[i] = t;
            out.prim[i] = scene.input_id(hit.prim);
            out.u[i] = hit.u;
            out.v[i] = hit.v;
            for (int a = 0; a < 3; ++a) out.normal[3 * i + static_cast<std::size_t>(a)] = nrm[a];
        };
        auto trace_one = [&](std::size_t i) {
            const WorldRay wr = load_ray(origins, directions, tmin, tmax, i);
            if (!ray_is_valid(wr)) return;  // invalid rays report a miss
            Hit hit;
            Ray ray = scene.to_local(wr);
            int entered = -1;
            if (!sections.empty() && !sections.clip(ray.org, ray.dir, ray.tmin, ray.tmax, entered)) return;
            if (closest_ray(scene, bvh, ray, hit, c)) store(i, hit, ray, entered);
        };
        std::size_t i = begin;
        if (sections.empty()) {
            constexpr int kMaxPackets = static_cast<int>(kBatch) / kPacket;
            Uninitialised<Ray, kBatch> ray_store;
            Uninitialised<Hit, kBatch> hit_store;
            Ray* rays = ray_store.data();
            Hit* hits = hit_store.data();
            // (Cleared only for GCC, which cannot see that entries past m are never read.)
            const Ray* rays_of[kMaxPackets] = {};
            Hit* hits_of[kMaxPackets] = {};
            int m = 0;
            for (; i + kPacket <= end; i += kPacket) {
                Ray* r = rays + (i - begin);
                bool packet = true;
                for (int k = 0; k < kPacket && packet; ++k) {
                    const std::size_t j = i + static_cast<std::size_t>(k);
                    const WorldRay wr = load_ray(origins, directions, tmin, tmax, j);
                    packet = ray_is_valid(wr) && same_vector(origins, i, j);
                    if (packet) new (r + k) Ray(scene.to_local(wr));
                }
                if (packet && packet_is_coherent(r, kPacket)) {
                    Hit* h = hits + (i - begin);
                    for (int k = 0; k < kPacket; ++k) new (h + k) Hit;
                    rays_of[m] = r;
                    hits_of[m++] = h;
                } else {
                    for (int k = 0; k < kPacket; ++k) trace_one(i + static_cast<std::size_t>(k));
                }
            }
            closest_packets<kPacket>(scene, bvh, interleave, rays_of, hits_of, m, c);
            for (int j = 0; j < m; ++j) {
                // A packet's rays and hits lie at its first ray's place in the batch.
                const std::size_t first = begin + static_cast<std::size_t>(rays_of[j] - rays);
                for (int k = 0; k < kPacket; ++k) {
                    const Hit& hit = hits_of[j][k];
                    if (hit.prim != kNoHit) store(first + static_cast<std::size_t>(k), hit, rays_of[j][k], -1);
                }
            }
        }
        for (; i < end; ++i) trace_one(i);
    }, threads);
    for (const auto& c : lane_counters) {
        out.counters.node_visits += c.node_visits;
        out.counters.triangle_tests += c.triangle_tests;
    }
    return out;
}

std::vector<std::uint8_t> occluded_scene(const Scene& scene, const double* origins, const double* directions,
                                         const double* tmin, const double* tmax, std::size_t n, unsigned threads) {
    // Every ray walks the wide BVH alone, several in flight. On the kd-tree, runs of rays
    // from one origin (the AO rays of a point) or along one direction (the shadow rays of
    // points towards a distant light) go as packets of up to 8, and on a large tree a
    // batch's packets go several in flight (occluded_packets).
    std::vector<std::uint8_t> out(n, 0);
    ThreadPool& pool = ThreadPool::global();
    if (const WideBvh* bvh = any_hit_bvh(scene)) {
        const bool interleave = interleaves(bvh->memory_bytes());
        pool.parallel_for((n + kBatch - 1) / kBatch, [&](std::size_t b, unsigned) {
            TraversalCounters c;
            const std::size_t first = b * kBatch, end = std::min(n, first + kBatch);
            occluded_wide_rays(
                *bvh, interleave, end - first,
                [&](std::size_t i, Ray& ray, std::uint32_t&) {
                    const WorldRay wr = load_ray(origins, directions, tmin, tmax, first + i);
                    if (!ray_is_valid(wr)) return false;  // invalid rays report a miss
                    ray = scene.to_local(wr);
                    return true;
                },
                [&](std::size_t i) { out[first + i] = 1; }, c);
        }, threads);
        return out;
    }
    constexpr int kPacket = 8;
    const bool interleave = interleaves(scene.tree().memory_bytes());
    pool.parallel_for((n + kBatch - 1) / kBatch, [&](std::size_t b, unsigned) {
        TraversalCounters c;
        const std::size_t end = std::min(n, (b + 1) * kBatch);
        struct Packet {
            Ray rays[kPacket];
            std::size_t first;
            int count;
        };
        Uninitialised<Packet, kBatch> store;  // (a batch holds at most kBatch runs)
        Packet* packets = store.data();
        const Ray* rays_of[kBatch];
        std::uint32_t masks[kBatch], blocked[kBatch];
        int m = 0;
        for (std::size_t i = b * kBatch; i < end;) {
            Packet& p = *new (packets + m) Packet;
            std::uint32_t mask = 0;
            int count = 0;
            // The run's shared vector: the origin, else (the next ray starting elsewhere)
            // the direction.
            const bool along = i + 1 < end && !same_vector(origins, i, i + 1) && same_vector(directions, i, i + 1);
            const double* shared = along ? directions : origins;
            for (; count < kPacket && i + static_cast<std::size_t>(count) < end; ++count) {
                const std::size_t j = i + static_cast<std::size_t>(count);
                if (!same_vector(shared, i, j)) break;
                const WorldRay wr = load_ray(origins, directions, tmin, tmax, j);
                if (!ray_is_valid(wr)) continue;  // invalid rays report a miss
                p.rays[count] = scene.to_local(wr);
                mask |= 1u << count;
            }
            count = std::max(count, 1);
            if (mask) {
                // Lanes outside the mask copy a live ray (the packet ignores them).
                const int any = __builtin_ctz(mask);
                for (int k = 0; k < kPacket; ++k) {
                    if (!(mask >> k & 1u)) p.rays[k] = p.rays[any];
                }
                p.first = i;
                p.count = count;
                rays_of[m] = p.rays;
                masks[m++] = mask;
            }
            i += static_cast<std::size_t>(count);
        }
        if (interleave) {
            occluded_packets<kPacket, kOcclusionInFlight>(scene.tree(), scene.tri_vertices(), rays_of, nullptr, masks,
                                                          blocked, m, c);
        } else {
            for (int j = 0; j < m; ++j) {
                blocked[j] = packets[j].count == 1 ? occluded_rays<1>(scene, packets[j].rays, nullptr, masks[j], c)
                                                   : occluded_rays<kPacket>(scene, packets[j].rays, nullptr, masks[j], c);
            }
        }
        for (int j = 0; j < m; ++j) {
            for (int k = 0; k < packets[j].count; ++k) {
                out[packets[j].first + static_cast<std::size_t>(k)] = (blocked[j] >> k & 1u) ? 1 : 0;
            }
        }
    }, threads);
    return out;
}

VASTRAY_KERNEL_END
