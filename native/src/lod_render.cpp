// The out-of-core renderer and ray queries, one build per ISA (isa.h): a built model in
// the block cache as a frame-loop backend (frame_renderer.h), and full-detail queries.
#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <utility>
#include <vector>

#include "vastray/frame_renderer.h"
#include "vastray/interleave.h"
#include "vastray/kernels.h"
#include "vastray/lod_render.h"
#include "vastray/lod_traverse_packet.h"

VASTRAY_KERNEL_BEGIN

namespace {

using lod_detail::load;

// One lane of a frame or ray batch over a cached model: the cache's frame protocol
// (tick, requests) for every lane.
std::vector<LodLane> make_lanes(BlockCache& cache, CachedModel& model, std::uint32_t tick) {
    const ModelIndex& index = model.index();
    std::vector<LodLane> lanes(ThreadPool::global().lanes());
    for (LodLane& lane : lanes) {
        lane.cache = &cache;
        lane.model = &model;
        lane.tick = tick;
        lane.level_first = index.level_first().data();
        lane.tri_level = static_cast<std::uint32_t>(index.level_count() - 1);
        lane.stream_first = index.stream_first().data();
        lane.tier_count = index.tier_count();
        lane.tiered = index.tiered();
        lane.has_colours = index.has_colours();
        lane.quantized_splits = index.quantized_splits();
        lane.packed_treelets = index.packed_treelets();
        lane.voxel_errors = index.voxel_errors();
        lane.quantized_vertices = index.quantized_vertices();
        lane.vertex_steps = index.vertex_steps();
        lane.compact_triangles = index.compact_triangles();
    }
    return lanes;
}

// Ends the frame `tick`: hands the lanes' block requests to the cache and adds up what
// the lanes saw. Also the exit path of a frame that throws (its requests reset the
// per-block request counters).
void close_frame(BlockCache& cache, std::uint32_t tick, const std::vector<LodLane>& lanes, FrameStats& stats,
                 std::size_t request_limit = 0) {
    std::vector<std::pair<CachedModel*, std::uint32_t>> requests;
    std::uint64_t missing = 0;
    for (const LodLane& lane : lanes) {
        requests.insert(requests.end(), lane.requests.begin(), lane.requests.end());
        stats.voxel_hits += lane.voxel_hits;
        stats.cache.lookups += lane.lookups;
        stats.cache.lookup_hits += lane.hits;
        stats.cache.working_set_blocks += lane.ws_blocks;
        stats.cache.working_set_bytes += lane.ws_bytes;
        stats.cache.bad_blocks += lane.bad;
        missing += lane.missing;
    }
    cache.end_frame(tick, requests, stats.cache, request_limit);
    stats.complete = missing == 0;
}

// Triangle block helpers shared by shading and ray queries.
format::TriangleBlockLayout triangle_layout(const std::uint8_t* tb, bool has_colours) {
    return format::TriangleBlockLayout::of(load<std::uint32_t>(tb), load<std::uint32_t>(tb + 4),
                                           load<std::uint32_t>(tb + 8), has_colours);
}

// A hit's triangle in a compact block (format.h): the traversal decoded the same
// fields when it tested it, so they are valid; indices are clamped all the same.
bool compact_triangle_of(const LodHit& hit, const ModelIndex& index, format::CompactTriangleBlock& b,
                         format::CompactTriangleBlock::Group& g) {
    return format::CompactTriangleBlock::parse(hit.tri_block, format::kBlockSize, index.has_colours(),
                                               index.quantized_vertices(), b) &&
           b.group(hit.local / format::compact::kGroup, g);
}

void triangle_of(const LodHit& hit, const ModelIndex& index, Vec3f* v) {
    if (index.compact_triangles()) {
        format::CompactTriangleBlock b{};
        format::CompactTriangleBlock::Group g{};
        std::uint32_t c[3] = {0, 0, 0};
        const bool ok = compact_triangle_of(hit, index, b, g);
        if (ok) b.corners(g, hit.local - g.first, c);
        for (int k = 0; k < 3; ++k) v[k] = ok ? b.vertex(std::min(c[k], b.verts - 1), index.vertex_steps()) : Vec3f(0, 0, 0);
        return;
    }
    const auto l = format::TriangleBlockLayout::read(hit.tri_block, index.has_colours(), index.quantized_vertices());
    const std::uint8_t* corner = hit.tri_block + l.triangles + 6 * std::size_t{hit.local};
    for (int k = 0; k < 3; ++k) {
        v[k] = lod_detail::plain_vertex(l, hit.tri_block, load<std::uint16_t>(corner + 2 * k), index.vertex_steps());
    }
}

// A secondary ray over a cached model: never reports the triangle it starts on.
struct ModelSecondary {
    LodRay ray;
    std::uint32_t skip = kNoHit;
};

// A built model in the block cache as a frame-loop backend (frame_renderer.h).
class ModelBackend {
public:
    using Ray = LodRay;
    using Hit = LodHit;
    using Lane = LodLane;
    using Secondary = ModelSecondary;

    ModelBackend(const ModelIndex& index, const Camera& camera, const RenderParams& params)
        : index_(index),
          camera_(camera),
          centre_(index.centre()),
          eye_(camera_.eye - centre_),
          root_(index.root_cell()),
          interleave_(interleaves(index.file_size())) {
        const Vec3f diag = root_.hi - root_.lo;
        ao_distance_ = params.ao_distance > 0 ? static_cast<float>(params.ao_distance) : 0.2f * length(diag);
        // Projected diameter 2R / (t * pixel_angle) <= PoE  <=>  R <= t * PoE * pixel_angle / 2.
        primary_cone_ = static_cast<float>(0.5 * params.pixels_of_error * camera_.pixel_angle);
        ao_cone_ = static_cast<float>(solid_angle_cone(params, camera_.pixel_angle));  // 0 at PoE 0
        if (camera_.orthographic) {
            camera_.start_behind(centre_ + Vec3d(root_.lo), centre_ + Vec3d(root_.hi));
            // A pixel is pixel_size wide at any depth: R <= PoE * pixel_size / 2. The cone
            // test (cone_t0 + t) * cone gives that when its apex lies so far back that the
            // model's depth changes the product by under 2^-20.
            const double reach = length(Vec3d(diag)) + length(camera_.eye - camera_.plane);
            primary_cone_t0_ = static_cast<float>(std::exp2(20.0) * std::max(reach, 1e-30));
            primary_cone_ = static_cast<float>(0.5 * params.pixels_of_error * camera_.pixel_size /
                                               static_cast<double>(primary_cone_t0_));
        }
    }

    Ray primary_ray(int x, int y) const { return primary_from(camera_.origin(x, y), camera_.direction(x, y)); }
    Box3f bounds() const { return root_; }
    void primary_rays4(int x0, int y, Ray* out) const {
        if (camera_.orthographic) {
            for (int k = 0; k < 4; ++k) out[k] = primary_ray(x0 + k, y);
            return;
        }
        Vec3d dirs[4];
        camera_.directions4(x0, y, dirs);
        for (int k = 0; k < 4; ++k) out[k] = primary_along(dirs[k]);
    }

    void trace(Lane& lane, const Ray& ray, Hit& hit) const { lod_traverse<false>(lane, root_, ray, hit); }
    void trace_stream(Lane& lane, const Ray* rays, Hit* hits, int n) const {
        lod_trace_stream(lane, root_, rays, hits, n);
    }

    template <int Side>
    bool trace_packet(Lane& lane, const Ray* rays, Hit* hits) const {
        constexpr int N = Side * Side;
        if (camera_.orthographic) return trace_parallel_packet<N>(lane, rays, hits);
        if (!lod_packet_is_coherent<N>(rays)) return false;
        lod_traverse_packet<N>(lane, root_, rays, hits);
        return true;
    }

    // On a large model (interleave.h) several packets in flight, so that their waits for
    // memory overlap; else one after the other.
    template <int Side>
    void trace_packets(Lane& lane, const Ray* const* rays, Hit* const* hits, bool* traced, int count) const {
        if (camera_.orthographic) {
            for (int j = 0; j < count; ++j) traced[j] = trace_parallel_packet<Side * Side>(lane, rays[j], hits[j]);
            return;
        }
        if (interleave_) {
            lod_trace_packets<Side * Side>(lane, root_, rays, hits, traced, count);
            return;
        }
        for (int j = 0; j < count; ++j) traced[j] = trace_packet<Side>(lane, rays[j], hits[j]);
    }

    // An orthographic camera's packet: one direction from origins apart, walked in the
    // order of the direction's signs (as shadow packets are), each ray with the single
    // ray's answer. A zero component (a front or top view) is taken too: every lane then
    // keeps to its origin's side of that axis's planes, and an origin on a plane sends the
    // lane into both children, lane by lane as a single ray goes (PacketSplit's flips).
    template <int N>
    bool trace_parallel_packet(Lane& lane, const Ray* rays, Hit* hits) const {
        const Vec3f& d = rays[0].ray.dir;
        std::uint32_t skip[N];
        for (int k = 0; k < N; ++k) {
            const Vec3f& dk = rays[k].ray.dir;
            if (dk.x != d.x || dk.y != d.y || dk.z != d.z || rays[k].cone != rays[0].cone ||
                rays[k].cone_t0 != rays[0].cone_t0) {
                return false;
            }
            skip[k] = kNoHit;
        }
        lod_packet_walk<N, false, LodPacketOrder::SharedSigns>(lane, root_, rays, hits, skip,
                                                               static_cast<std::uint32_t>((1ull << N) - 1));
        return true;
    }

    std::int32_t prim_id(const Hit& hit) const {
        return hit.prim == kVoxelPrim ? kPrimVoxel : static_cast<std::int32_t>(hit.prim);
    }

    void surface(const Hit& hit, Vec3f& n, Vec3f& colour) const {
        if (hit.prim == kVoxelPrim) {
            format::unpack_sample(hit.sample, colour, n);
            if (!index_.has_colours()) colour = shading::default_colour();
            return;
        }
        Vec3f v[3];
        triangle_of(hit, index_, v);
        n = normalize(cross(v[1] - v[0], v[2] - v[0]));
        colour = shading::default_colour();
        if (index_.has_colours()) {
            const std::uint32_t c = colour_of(hit);
            colour = Vec3f(static_cast<float>(c & 0xffu), static_cast<float>((c >> 8) & 0xffu),
                           static_cast<float>((c >> 16) & 0xffu)) *
                     (1.0f / 255.0f);
        }
    }

    // A secondary ray leaving a hit. LOD rays must clear the voxels of their own
    // surface: a triangle's ray skips what a cone of this footprint would accept around
    // its origin, a voxel's ray starts outside the voxel (offset grows with its size).
    // Shadow rays continue the cone of the ray that found the hit (PoE metric for a
    // primary ray's); AO and diffuse rays have cones of their own (solid-angle metric).
    // A diffuse ray's cone starts at the incoming ray's footprint at the hit: near its
    // origin it sees the model no finer than the ray that found the hit. Started as a
    // point, every diffuse ray went down to the leaves around its origin: at the 10^8
    // overview that read 2 GiB where the view reads 256 MiB, for the same image error
    // (docs/out-of-core-rendering.md, "Frames and modes"). AO rays still start as a
    // point: they measure the occlusion close to their origin, and the footprint made
    // AO visibly lighter there.
    Secondary secondary_ray(const Ray& incoming, const Hit& hit, const Vec3f& n, const Vec3f& dir, float tmax,
                            SecondaryRay kind) const {
        Secondary s;
        LodRay& r = s.ray;
        r.ray.dir = dir;
        r.ray.tmax = tmax;
        const bool shadow = kind == SecondaryRay::Shadow;
        r.cone = shadow ? incoming.cone : ao_cone_;
        r.cone_t0 = shadow ? incoming.cone_t0 + hit.t : 0.0f;
        if (kind == SecondaryRay::Diffuse && r.cone > 0) {
            r.cone_t0 = incoming.cone * (incoming.cone_t0 + hit.t) / r.cone;  // footprint radius / cone slope
        }
        if (hit.prim == kVoxelPrim) {
            r.ray.org = incoming.ray.org + incoming.ray.dir * hit.t + n * (2.0f * hit.voxel_radius);
            r.ray.tmin = 0;
        } else {
            Vec3f v[3];
            triangle_of(hit, index_, v);
            r.ray.org = shading::offset_origin(v, hit, n);
            r.ray.tmin = 2.5f * r.cone_t0 * r.cone;
            s.skip = hit.prim;
        }
        return s;
    }

    // Any hits (voxels count): one ray singly, more as a packet, sharing an origin (the
    // AO rays of a pixel) or a direction (shadow rays). Lanes outside `mask` copy a
    // live ray and are ignored.
    template <int N>
    std::uint32_t occluded(Lane& lane, const Secondary* rays, std::uint32_t mask, RayGroup group) const {
        if constexpr (N == 1) {
            LodHit occluder;
            return (mask & 1u) && lod_traverse<true>(lane, root_, rays[0].ray, occluder, rays[0].skip) ? 1u : 0u;
        } else {
            LodRay r[N];
            LodHit scratch[N];
            std::uint32_t skip[N];
            const int any = __builtin_ctz(mask);
            for (int i = 0; i < N; ++i) {
                const Secondary& s = rays[(mask >> i & 1u) ? i : any];
                r[i] = s.ray;
                skip[i] = s.skip;
            }
            return group == RayGroup::SharedOrigin
                       ? lod_packet_walk<N, true, LodPacketOrder::SharedOrigin>(lane, root_, r, scratch, skip, mask)
                       : lod_packet_walk<N, true, LodPacketOrder::SharedSigns>(lane, root_, r, scratch, skip, mask);
        }
    }

    // Several occlusion queries, one after the other: their packets in flight measured
    // 0.85-1.0x at 10^7 and 10^8 (AO frames), where primary packets gain.
    template <int N>
    void occluded_group(Lane& lane, const Secondary* const* rays, const std::uint32_t* mask, std::uint32_t* blocked,
                        int count, RayGroup group) const {
        for (int j = 0; j < count; ++j) blocked[j] = mask[j] ? occluded<N>(lane, rays[j], mask[j], group) : 0u;
    }

    // Closest hits of the rays in `mask` (a block's diffuse rays): those whose direction
    // components agree in sign go as packets of up to 8 (lod_packet_walk, SharedSigns:
    // each ray still meets its cells in its own order, so its hit is the single ray's),
    // the rest singly. The rays of neighbouring pixels start close together, so a
    // packet's walk down to their origins is shared.
    template <int N>
    void trace_secondary(Lane& lane, const Secondary* rays, Hit* hits, std::uint32_t mask) const {
        constexpr int kPacket = 8;
        auto single = [&](int i) { lod_traverse<false>(lane, root_, rays[i].ray, hits[i], rays[i].skip); };
        if constexpr (N < 4) {
            for (; mask; mask &= mask - 1) single(__builtin_ctz(mask));
        } else {
            std::uint32_t octant[8] = {};
            for (; mask; mask &= mask - 1) {
                const int i = __builtin_ctz(mask);
                const Vec3f& d = rays[i].ray.ray.dir;
                if (d.x == 0.0f || d.y == 0.0f || d.z == 0.0f) {
                    single(i);
                    continue;
                }
                octant[(d.x < 0.0f ? 1 : 0) | (d.y < 0.0f ? 2 : 0) | (d.z < 0.0f ? 4 : 0)] |= 1u << i;
            }
            for (std::uint32_t rest : octant) {
                while (rest) {
                    if (__builtin_popcount(rest) == 1) {
                        single(__builtin_ctz(rest));
                        break;
                    }
                    LodRay r[kPacket];
                    LodHit h[kPacket];
                    std::uint32_t skip[kPacket];
                    int index[kPacket], n = 0;
                    for (; rest && n < kPacket; rest &= rest - 1, ++n) {
                        index[n] = __builtin_ctz(rest);
                        r[n] = rays[index[n]].ray;
                        skip[n] = rays[index[n]].skip;
                    }
                    for (int k = n; k < kPacket; ++k) {  // lanes outside the mask copy a traced ray
                        r[k] = r[0];
                        skip[k] = skip[0];
                    }
                    lod_packet_walk<kPacket, false, LodPacketOrder::SharedSigns>(lane, root_, r, h, skip,
                                                                                 (1u << n) - 1);
                    for (int k = 0; k < n; ++k) hits[index[k]] = h[k];
                }
            }
        }
    }

    float ao_distance() const { return ao_distance_; }
    Vec3d centre() const { return centre_; }

private:
    // A hit triangle's colour, 0x00BBGGRR.
    std::uint32_t colour_of(const Hit& hit) const {
        if (index_.compact_triangles()) {
            format::CompactTriangleBlock b{};
            format::CompactTriangleBlock::Group g{};
            if (!compact_triangle_of(hit, index_, b, g)) return 0;
            return b.colour(std::min(b.palette_index(g, hit.local - g.first), b.palette_size - 1));
        }
        const auto l = triangle_layout(hit.tri_block, true);
        return load<std::uint32_t>(hit.tri_block + l.colours + 4 * std::size_t{hit.local});
    }
    // The primary ray from the eye along world direction `dir`, in the local float frame.
    Ray primary_along(const Vec3d& dir) const {
        LodRay r;
        r.ray.org = eye_;
        r.ray.dir = Vec3f(dir);
        r.cone = primary_cone_;
        return r;
    }
    // An orthographic camera's ray from its own point, in the local frame as the eye is.
    Ray primary_from(const Vec3d& org, const Vec3d& dir) const {
        if (!camera_.orthographic) return primary_along(dir);
        LodRay r = primary_along(dir);
        r.ray.org = Vec3f(org - centre_);
        r.cone_t0 = primary_cone_t0_;
        return r;
    }

    const ModelIndex& index_;
    shading::CameraRays camera_;
    Vec3d centre_;
    Vec3f eye_;  // the eye in the local float frame (the centre subtracted in double, as the in-core scene does)
    Box3f root_;
    bool interleave_;
    float ao_distance_ = 1, primary_cone_ = 0, primary_cone_t0_ = 0, ao_cone_ = 0;
};

}  // namespace

Frame render_model(BlockCache& cache, CachedModel& model, const Camera& camera, const RenderParams& params) {
    camera.validate();
    params.validate();
    const FrameClock clock;
    Frame frame;
    shading::blank_frame(frame, camera, params.threads);
    const ModelBackend backend(model.index(), camera, params);
    const std::uint32_t tick = cache.begin_frame(frame.stats.cache);
    std::vector<LodLane> lanes = make_lanes(cache, model, tick);
    try {
        trace_frame(backend, camera, params, params.packets_or(16), lanes, frame);
    } catch (...) {
        close_frame(cache, tick, lanes, frame.stats);
        throw;
    }
    close_frame(cache, tick, lanes, frame.stats, static_cast<std::size_t>(params.request_limit));
    clock.stop(params, frame.stats);
    return frame;
}

LodRayHits intersect_model(BlockCache& cache, CachedModel& model, const double* origins, const double* directions,
                           const double* tmin, const double* tmax, std::size_t n, unsigned threads,
                           const std::vector<SectionPlane>& planes) {
    const FrameClock clock;
    const ModelIndex& index = model.index();
    const Vec3d centre = index.centre();
    const LocalSections sections(planes, centre);
    const Box3f root = index.root_cell();
    LodRayHits out;
    out.t.assign(n, std::numeric_limits<double>::infinity());
    out.position.assign(3 * n, std::numeric_limits<double>::quiet_NaN());
    out.normal.assign(3 * n, 0.0f);
    out.prim.assign(n, kPrimBackground);
    out.u.assign(n, 0.0f);
    out.v.assign(n, 0.0f);
    out.complete.assign(n, 1);
    const std::uint32_t tick = cache.begin_frame(out.stats.cache);
    std::vector<LodLane> lanes = make_lanes(cache, model, tick);
    constexpr std::size_t kBatch = 256;
    auto trace_batch = [&](std::size_t b, unsigned lane_index) {
        LodLane& lane = lanes[lane_index];
        for (std::size_t i = b * kBatch; i < std::min(n, (b + 1) * kBatch); ++i) {
            const Vec3d o(origins[3 * i], origins[3 * i + 1], origins[3 * i + 2]);
            const Vec3d d(directions[3 * i], directions[3 * i + 1], directions[3 * i + 2]);
            if (!all_finite(o) || !all_finite(d) || !(dot(d, d) > 0) || std::isnan(tmin[i]) || std::isnan(tmax[i])) {
                continue;  // an invalid ray reports a miss
            }
            // Unit direction in double, so t is a distance in world units.
            const Vec3d unit = normalize(d);
            LodRay r;  // cone 0: full detail
            r.ray.org = Vec3f(o - centre);
            r.ray.dir = Vec3f(unit);
            r.ray.tmin = static_cast<float>(tmin[i] * length(d));
            r.ray.tmax = static_cast<float>(std::min(tmax[i] * length(d), 3.4e38));
            int entered = -1;
            if (!sections.empty() && !sections.clip(r.ray.org, r.ray.dir, r.ray.tmin, r.ray.tmax, entered)) {
                continue;  // all of it on the cut side: a miss
            }
            const std::uint64_t missing_before = lane.missing;
            LodHit hit;
            lod_traverse<false>(lane, root, r, hit);
            if (lane.missing != missing_before || hit.prim == kVoxelPrim) {
                out.complete[i] = 0;
                continue;
            }
            if (hit.prim == kNoHit) continue;
            Vec3f v[3];
            triangle_of(hit, index, v);
            // The hit point from barycentrics in the local float frame, then to world in
            // double: exact to the triangle's own float precision, far from the origin too.
            Vec3f local = v[0] * (1.0f - hit.u - hit.v) + v[1] * hit.u + v[2] * hit.v;
            Vec3f nrm = normalize(cross(v[1] - v[0], v[2] - v[0]));
            if (entered >= 0 && dot(nrm, r.ray.dir) > 0) {
                // In a cut solid: its cap, on the plane.
                local = r.ray.org + r.ray.dir * r.ray.tmin;
                nrm = -sections.normal(entered);
            }
            const Vec3d world = centre + Vec3d(local);
            out.t[i] = length(world - o);
            out.prim[i] = static_cast<std::int64_t>(hit.prim);
            out.u[i] = hit.u;
            out.v[i] = hit.v;
            for (int a = 0; a < 3; ++a) {
                out.position[3 * i + static_cast<std::size_t>(a)] = world[a];
                out.normal[3 * i + static_cast<std::size_t>(a)] = nrm[a];
            }
        }
    };
    try {
        ThreadPool::global().parallel_for((n + kBatch - 1) / kBatch, trace_batch, threads);
    } catch (...) {
        close_frame(cache, tick, lanes, out.stats);
        throw;
    }
    out.stats.primary_rays = n;
    for (const LodLane& lane : lanes) {
        out.stats.node_visits += lane.node_visits;
        out.stats.triangle_tests += lane.triangle_tests;
    }
    close_frame(cache, tick, lanes, out.stats);
    RenderParams p;
    p.threads = threads;
    clock.stop(p, out.stats);
    return out;
}

VASTRAY_KERNEL_END
