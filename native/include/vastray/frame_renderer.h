// The one frame loop of both renderers: tiles over the thread pool, primary rays in
// packets or singly, and the shading of every mode, secondary rays included. A renderer
// supplies only its traversal, as a Backend:
//
//   using Ray = ...; using Hit = ...;   // Hit derives from vastray::Hit (t, prim, u, v)
//   using Lane = ...;                   // per-thread traversal state; has node_visits
//                                       // and triangle_tests counters
//   using Secondary = ...;              // a secondary ray: has `ray`, a Ray
//   Ray primary_ray(int x, int y) const;
//   Box3f bounds() const;                                           // the model's box, in the rays' frame
//   void primary_rays4(int x0, int y, Ray* out) const;              // primary_ray of (x0 + k, y), k < 4
//   void trace(Lane&, const Ray&, Hit&) const;                       // closest hit
//   void trace_stream(Lane&, const Ray*, Hit*, int n) const;        // n closest hits, as trace
//       // gives them; the backend may keep several rays in flight to overlap memory waits
//   template <int Side> bool trace_packet(Lane&, const Ray*, Hit*) const;
//       // Side x Side rays in row order; false (nothing traced) when not coherent
//   template <int Side> void trace_packets(Lane&, const Ray* const* rays, Hit* const* hits,
//                                          bool* traced, int count) const;
//       // count such packets, which the backend may keep in flight together; traced[j]
//       // as trace_packet would return for packet j
//   std::int32_t prim_id(const Hit&) const;                          // what Frame::prim holds
//   void surface(const Hit&, Vec3f& unit_normal, Vec3f& colour) const;
//   Secondary secondary_ray(const Ray& incoming, const Hit&, const Vec3f& n, const Vec3f& dir,
//                           float tmax, SecondaryRay kind) const;  // leaving a hit
//   template <int N> std::uint32_t occluded(Lane&, const Secondary* rays, std::uint32_t mask,
//                                           RayGroup group) const;
//       // any hit of the rays selected by mask (N = 1, 4, 8 or 16): the bits of those blocked
//   template <int N> void occluded_group(Lane&, const Secondary* const* rays, const std::uint32_t* mask,
//                                        std::uint32_t* blocked, int count, RayGroup group) const;
//       // count such queries (a mask may be 0: nothing blocked), which the backend may keep
//       // in flight together; blocked[j] as occluded would return for query j
//   template <int N> void trace_secondary(Lane&, const Secondary* rays, Hit* hits,
//                                        std::uint32_t mask) const;
//       // closest hits (diffuse rays) of the rays selected by mask (N <= 32), whatever their
//       // origins and directions: hits[i] as a single ray would find it
//   float ao_distance() const;
//
// Both backends trace the same rays (CameraRays) and shade them with the same terms,
// so a full-detail out-of-core image equals the in-core one pixel for pixel. Secondary
// rays go to the backend in groups that share an origin (the AO rays of a pixel) or a
// direction (the shadow rays of a pixel block), which its packets exploit; any-hit
// answers do not depend on how rays are grouped.
#pragma once

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <limits>
#include <memory>
#include <vector>

#include "vastray/denoise.h"
#include "vastray/isa.h"
#include "vastray/render.h"
#include "vastray/scratch.h"
#include "vastray/shading.h"

VASTRAY_KERNEL_BEGIN

// Shadow rays continue the cone of the ray that found the hit (PoE metric); AO and
// diffuse rays have their own (solid-angle metric), a diffuse ray's starting at the
// footprint of the ray that found the hit.
enum class SecondaryRay { Shadow, AmbientOcclusion, Diffuse };
// How the rays of one occlusion query relate.
enum class RayGroup { SharedOrigin, SharedDirection };

// Section planes in a renderer's local float frame (its model centre subtracted in
// double, as rays are). A plane keeps the points q with dot(n, q) + d >= 0.
class LocalSections {
public:
    LocalSections(const std::vector<SectionPlane>& planes, const Vec3d& centre) {
        for (const SectionPlane& p : planes) {
            const double len = length(p.normal);
            const Vec3d n = p.normal * (1.0 / len);
            planes_.push_back({Vec3f(n), static_cast<float>((p.offset + dot(p.normal, centre)) / len)});
        }
    }

    bool empty() const { return planes_.empty(); }
    const Vec3f& normal(int plane) const { return planes_[static_cast<std::size_t>(plane)].n; }

    // Narrows [tmin, tmax] of the ray org + t dir to the part on the kept side of every
    // plane; false when nothing is left. `entered` is the plane the ray crosses into
    // the kept side at the new tmin, or -1 when tmin did not move.
    bool clip(const Vec3f& org, const Vec3f& dir, float& tmin, float& tmax, int& entered) const {
        entered = -1;
        for (std::size_t i = 0; i < planes_.size(); ++i) {
            const Plane& p = planes_[i];
            const float f0 = dot(p.n, org) + p.d, dn = dot(p.n, dir);
            if (dn == 0.0f) {
                if (f0 < 0.0f) return false;  // parallel, on the cut side
                continue;
            }
            const float t = -f0 / dn;
            if (dn > 0.0f) {
                if (t > tmin) {
                    tmin = t;
                    entered = static_cast<int>(i);
                }
            } else if (t < tmax) {
                tmax = t;
            }
        }
        return tmin <= tmax;
    }

private:
    struct Plane {
        Vec3f n;
        float d;
    };
    std::vector<Plane> planes_;
};

// A cut solid's cap: flat, in a colour no model part has by default, lit from the eye.
inline Vec3f cap_colour() { return {0.86f, 0.38f, 0.26f}; }
// With a highlight set, as CAD viewers ghost the rest: highlighted triangles are blended
// towards a saturated blue, strongly enough to find a small part, weakly enough to keep
// its shading; everything else (LOD voxels too) turns a light, flat grey, since a model's
// own colours (blue pipes, say) would otherwise hide the highlight among them.
inline Vec3f highlighted(const Vec3f& colour) {
    constexpr float kMix = 0.7f;
    return colour * (1 - kMix) + Vec3f(0.1f, 0.45f, 1.0f) * kMix;
}
inline Vec3f ghosted(const Vec3f& colour) {
    const float luma = 0.3f * colour.x + 0.59f * colour.y + 0.11f * colour.z;
    const float grey = 0.55f + 0.3f * luma;
    return {grey, grey, grey};
}

// Rays traced by one lane; node and triangle counts live in the backend's lane. Each
// lane's on a cache line of its own (no false sharing between threads).
struct alignas(64) LaneRays {
    std::uint64_t primary = 0, secondary = 0;
};

// Per-pixel terms of the indirect mode, kept until the whole frame is traced: the
// filter needs every pixel's neighbours.
struct IndirectTerms {
    std::vector<float> albedo, direct, light, normal;  // 3, 1, 3, 3 floats per pixel

    explicit IndirectTerms(std::size_t pixels)
        : albedo(3 * pixels, 0.0f), direct(pixels, 0.0f), light(3 * pixels, 0.0f), normal(3 * pixels, 0.0f) {}
};

template <typename Backend>
class FrameShader {
public:
    using Ray = typename Backend::Ray;
    using Hit = typename Backend::Hit;
    using Lane = typename Backend::Lane;
    using Secondary = typename Backend::Secondary;

    FrameShader(const Backend& backend, const RenderParams& params, const Camera& camera, int packets, Frame& frame,
                IndirectTerms* indirect, const LocalSections& sections)
        : backend_(backend), params_(params), packets_(packets), frame_(frame), indirect_(indirect),
          sections_(sections), sun_(Vec3f(normalize(params.sun_direction))), up_(Vec3f(camera.up)),
          orthographic_(camera.orthographic) {
        up_ = normalize(up_);
        // The model's box seen from the eye, for may_enter_model: the same for every tile.
        const Box3f box = backend_.bounds();
        cull_tiles_ = !box.empty() && all_finite(box.lo) && all_finite(box.hi);
        if (cull_tiles_) {
            const Vec3d eye(origin(backend_.primary_ray(0, 0)));
            first_origin_ = eye;
            const double margin = 1e-4 * length(Vec3d(box.hi) - Vec3d(box.lo));
            for (int k = 0; k < 8; ++k) {
                const Vec3d c((k & 1) ? box.hi.x : box.lo.x, (k & 2) ? box.hi.y : box.lo.y,
                              (k & 4) ? box.hi.z : box.lo.z);
                to_corner_[k] = c - eye;
                corner_slack_[k] = 1e-4 * length(to_corner_[k]) + margin;
            }
        }
    }

    void render_tile(int x0, int y0, int x1, int y1, Lane& lane, LaneRays& rays) const {
        if (!may_enter_model(x0, y0, x1, y1)) {
            // Every ray of the tile misses the model: its pixels are background, as the
            // walks would have found ray by ray.
            for (int y = y0; y < y1; ++y) {
                for (int x = x0; x < x1; ++x) shading::background(y, frame_.height, frame_.rgb.data() + 3 * pixel(x, y));
            }
            rays.primary += static_cast<std::uint64_t>(x1 - x0) * static_cast<std::uint64_t>(y1 - y0);
            return;
        }
        if (packets_ == 1) {
            stream_tile(x0, y0, x1, y1, lane, rays);
            return;
        }
        // The tile's whole 4x4 blocks go to the backend a group at a time; blocks cut by
        // the tile's edge go as quads and single rays.
        int xs[kPacketGroup], ys[kPacketGroup], m = 0;
        for (int y = y0; y < y1; y += 4) {
            for (int x = x0; x < x1; x += 4) {
                if (packets_ == 16 && x + 3 < x1 && y + 3 < y1) {
                    xs[m] = x;
                    ys[m++] = y;
                    if (m == kPacketGroup) {
                        trace_packet_group(xs, ys, m, x1, y1, lane, rays);
                        m = 0;
                    }
                } else {
                    trace_quads(x, y, x1, y1, lane, rays);
                }
            }
        }
        if (m > 0) trace_packet_group(xs, ys, m, x1, y1, lane, rays);
    }

private:
    // A block of primary hits being shaded together (one packet, or one pixel).
    template <int P>
    struct Block {
        int x[P], y[P];
        Ray ray[P];
        Hit hit[P];
        Vec3f n[P], colour[P];
        int entered[P];         // the section plane a ray entered the kept side through, or -1
        std::uint32_t lit = 0;  // pixels that see the model
        std::uint32_t marked = 0;  // pixels that see a highlighted triangle
    };

    // 4x4 packets handed to the backend together (trace_packets), so that it can overlap
    // their memory waits (the in-core backend keeps 8 in flight on large trees): up to a
    // whole 16x16 tile. (Groups of 4, a tile's row, measured 0.93-0.97x groups of 16.)
    static constexpr int kPacketGroup = 16;

    template <int N>
    void primary_block(Block<N>& b, int x, int y, int side) const {
        b.lit = b.marked = 0;
        for (int i = 0; i < N; ++i) {
            b.x[i] = x + i % side;
            b.y[i] = y + i / side;
        }
        if (side == 4) {
            for (int r = 0; r < 4; ++r) backend_.primary_rays4(x, y + r, b.ray + 4 * r);
        } else {
            for (int i = 0; i < N; ++i) b.ray[i] = backend_.primary_ray(b.x[i], b.y[i]);
        }
        // Section planes narrow each ray to its own segment on the kept side, which the
        // packet walks take lane by lane as single rays do. A ray left with nothing gets
        // an empty segment: it enters no cell, and its pixel stays background.
        for (int i = 0; i < N; ++i) {
            if (!clip(b.ray[i], b.entered[i])) base(b.ray[i]).tmin = std::numeric_limits<float>::infinity();
        }
    }

    template <int Side>
    bool trace_packet(int x, int y, Lane& lane, LaneRays& rays) const {
        constexpr int N = Side * Side;
        Block<N> b;
        primary_block(b, x, y, Side);
        if (!backend_.template trace_packet<Side>(lane, b.ray, b.hit)) return false;
        rays.primary += N;
        shade(b, lane, rays);
        return true;
    }

    // The 4x4 blocks at (xs[j], ys[j]), j < m; a block that is not coherent goes as 2x2
    // quads and single rays, as it would alone.
    void trace_packet_group(const int* xs, const int* ys, int m, int x1, int y1, Lane& lane, LaneRays& rays) const {
        // Left uninitialised: primary_block and the walk write every field before shading
        // reads it, and clearing 16 blocks (about 40 KB) for every group cost about 2 % of
        // a frame.
        Uninitialised<Block<16>, kPacketGroup> store;
        Block<16>* blocks = store.data();
        const Ray* ray_of[kPacketGroup];
        Hit* hit_of[kPacketGroup];
        bool traced[kPacketGroup];
        for (int j = 0; j < m; ++j) {
            primary_block(blocks[j], xs[j], ys[j], 4);
            ray_of[j] = blocks[j].ray;
            hit_of[j] = blocks[j].hit;
        }
        backend_.template trace_packets<4>(lane, ray_of, hit_of, traced, m);
        for (int j = 0; j < m; ++j) {
            if (traced[j]) {
                rays.primary += 16;
                shade(blocks[j], lane, rays);
            } else {
                trace_quads(xs[j], ys[j], x1, y1, lane, rays);
            }
        }
    }

    // The 4x4 block at (x, y), clipped to the tile: 2x2 packets where coherent, else rays.
    void trace_quads(int x, int y, int x1, int y1, Lane& lane, LaneRays& rays) const {
        for (int qy = y; qy < std::min(y + 4, y1); qy += 2) {
            for (int qx = x; qx < std::min(x + 4, x1); qx += 2) {
                if (packets_ >= 4 && qx + 1 < x1 && qy + 1 < y1 && trace_packet<2>(qx, qy, lane, rays)) continue;
                for (int py = qy; py < std::min(qy + 2, y1); ++py) {
                    for (int px = qx; px < std::min(qx + 2, x1); ++px) trace_single(px, py, lane, rays);
                }
            }
        }
    }

    // Single rays: the tile's primary rays go to the backend a run at a time, which traces
    // them as it likes (several in flight), and are then shaded pixel by pixel.
    void stream_tile(int x0, int y0, int x1, int y1, Lane& lane, LaneRays& rays) const {
        constexpr int kRun = 256;
        // Left uninitialised: default member initialisers would clear the three arrays
        // (some 60 KB) for every tile, and every element is written before it is read.
        Uninitialised<Block<1>, kRun> px_store;
        Uninitialised<Ray, kRun> traced_store;
        Uninitialised<Hit, kRun> hits_store;
        Block<1>* px = px_store.data();
        Ray* traced = traced_store.data();
        Hit* hits = hits_store.data();
        int slot[kRun];
        const int width = x1 - x0, pixels = width * (y1 - y0);
        for (int p0 = 0; p0 < pixels; p0 += kRun) {
            const int count = std::min(kRun, pixels - p0);
            int n = 0;
            for (int k = 0; k < count; ++k) {
                Block<1>& b = *new (px + k) Block<1>;  // (only its masks have initialisers)
                b.x[0] = x0 + (p0 + k) % width;
                b.y[0] = y0 + (p0 + k) / width;
                b.ray[0] = backend_.primary_ray(b.x[0], b.y[0]);
                b.hit[0].prim = kNoHit;  // stays so when the whole ray lies on the cut side
                if (clip(b.ray[0], b.entered[0])) {
                    new (traced + n) Ray(b.ray[0]);
                    new (hits + n) Hit;
                    slot[n++] = k;
                }
            }
            backend_.trace_stream(lane, traced, hits, n);
            for (int j = 0; j < n; ++j) px[slot[j]].hit[0] = hits[j];
            rays.primary += static_cast<std::uint64_t>(count);
            for (int k = 0; k < count; ++k) shade(px[k], lane, rays);
        }
    }

    void trace_single(int x, int y, Lane& lane, LaneRays& rays) const {
        Block<1> b;
        b.x[0] = x;
        b.y[0] = y;
        b.ray[0] = backend_.primary_ray(x, y);
        b.entered[0] = -1;
        ++rays.primary;
        if (clip(b.ray[0], b.entered[0])) {
            backend_.trace(lane, b.ray[0], b.hit[0]);
        } else {
            b.hit[0].prim = kNoHit;  // the whole ray lies on the cut side
        }
        shade(b, lane, rays);
    }

    // Sections: narrows a ray to the kept side; false when nothing is left.
    template <typename R>
    bool clip(R& r, int& entered) const {
        entered = -1;
        if (sections_.empty()) return true;
        vastray::Ray& ray = base(r);
        return sections_.clip(ray.org, ray.dir, ray.tmin, ray.tmax, entered);
    }
    bool clip_secondary(Secondary& s) const {
        int entered;
        return clip(s.ray, entered);
    }

    std::size_t pixel(int x, int y) const { return static_cast<std::size_t>(y) * frame_.width + x; }

    // False when no primary ray of the tile [x0, x1) x [y0, y1) can enter the model's box.
    // The tile's rays leave the eye through the rectangle of its corner pixels, so they lie
    // in the pyramid of the four corner rays; the tile is out when the whole box lies
    // beyond one side of that pyramid, or behind the eye, by a margin far wider than the
    // float error of the rays' directions (relative 1e-4 of each corner's distance) and
    // the walks' slack.
    // (The rays of an overview that miss the model cost the frame loop ray set-up, a
    // packet start and shading, pixel by pixel.)
    bool may_enter_model(int x0, int y0, int x1, int y1) const {
        if (!cull_tiles_) return true;
        const Ray corner_rays[4] = {backend_.primary_ray(x0, y0), backend_.primary_ray(x1 - 1, y0),
                                    backend_.primary_ray(x1 - 1, y1 - 1), backend_.primary_ray(x0, y1 - 1)};
        Vec3d dirs[4], centre(0, 0, 0);
        for (int i = 0; i < 4; ++i) {
            dirs[i] = Vec3d(direction(corner_rays[i]));
            centre += dirs[i];
        }
        if (orthographic_) return may_enter_model_parallel(corner_rays, dirs[0]);
        // Behind the eye: the rays go forward from it (t >= 0), so when every corner ray
        // leaves at under 90 degrees from their mean, so does every ray of the tile, and a box
        // wholly behind the plane through the eye across that mean is out of reach.
        bool forward = true;
        for (const Vec3d& d : dirs) forward = forward && dot(centre, d) > 0;
        bool behind = forward;
        for (int k = 0; k < 8 && behind; ++k) behind = dot(centre, to_corner_[k]) < -corner_slack_[k] * length(centre);
        if (behind) return false;
        for (int i = 0; i < 4; ++i) {
            Vec3d side = cross(dirs[i], dirs[(i + 1) % 4]);
            const double len = length(side);
            if (!(len > 0)) continue;  // a tile one pixel wide or high: no side here
            side = side / len;
            if (dot(side, centre) < 0) side = -side;  // pointing into the pyramid
            bool beyond = true;
            for (int k = 0; k < 8 && beyond; ++k) beyond = dot(side, to_corner_[k]) < -corner_slack_[k];
            if (beyond) return false;
        }
        return true;
    }

    // may_enter_model for an orthographic camera: the tile's rays are parallel and start
    // in the rectangle of its corner rays' origins, so they lie in the prism those rays
    // span, and start behind the whole box (CameraRays::start_behind).
    bool may_enter_model_parallel(const Ray (&corner_rays)[4], const Vec3d& dir) const {
        Vec3d orgs[4], middle(0, 0, 0);
        for (int i = 0; i < 4; ++i) {
            orgs[i] = Vec3d(origin(corner_rays[i]));
            middle += orgs[i] * 0.25;
        }
        for (int i = 0; i < 4; ++i) {
            Vec3d side = cross(dir, orgs[(i + 1) % 4] - orgs[i]);
            const double len = length(side);
            if (!(len > 0)) continue;  // a tile one pixel wide or high: no side here
            side = side / len;
            if (dot(side, middle - orgs[i]) < 0) side = -side;  // pointing into the prism
            const Vec3d shift = orgs[i] - first_origin_;
            bool beyond = true;
            for (int k = 0; k < 8 && beyond; ++k) beyond = dot(side, to_corner_[k] - shift) < -corner_slack_[k];
            if (beyond) return false;
        }
        return true;
    }

    template <int P>
    void shade(Block<P>& b, Lane& lane, LaneRays& rays) const {
        for (int i = 0; i < P; ++i) {
            const std::size_t px = pixel(b.x[i], b.y[i]);
            if (b.hit[i].prim == kNoHit) {
                shading::background(b.y[i], frame_.height, frame_.rgb.data() + 3 * px);
                continue;
            }
            b.lit |= 1u << i;
            frame_.depth[px] = b.hit[i].t;
            frame_.prim[px] = backend_.prim_id(b.hit[i]);
            backend_.surface(b.hit[i], b.n[i], b.colour[i]);
            const Vec3f& dir = direction(b.ray[i]);
            if (!sections_.empty() && b.entered[i] >= 0 && dot(b.n[i], dir) > 0) {
                // The ray came in through a plane and meets a surface from behind: it is
                // inside a cut solid, and sees the cap on the plane.
                const Vec3f cap_n = -sections_.normal(b.entered[i]);
                frame_.depth[px] = base(b.ray[i]).tmin;
                frame_.prim[px] = kPrimCap;
                b.lit &= ~(1u << i);
                const Vec3f c = params_.shading == Shading::Normal ? (cap_n + Vec3f(1, 1, 1)) * 0.5f
                                                                   : cap_colour() * shading::headlight(cap_n, dir);
                shading::store_rgb(c, frame_.rgb.data() + 3 * px);  // (compose_indirect leaves caps)
                continue;
            }
            if (params_.shading != Shading::Normal && dot(b.n[i], dir) > 0) {
                b.n[i] = -b.n[i];  // shade the side the viewer sees
            }
            if (!params_.highlight.empty()) {  // (the albedo changes, so every mode lights it)
                if (in_ranges(params_.highlight, frame_.prim[px])) {
                    b.marked |= 1u << i;
                    b.colour[i] = highlighted(b.colour[i]);
                } else {
                    b.colour[i] = ghosted(b.colour[i]);
                }
            }
        }
        if (!b.lit) return;
        float light[P];
        switch (params_.shading) {
            case Shading::Normal:
                for (int i = 0; i < P; ++i) {
                    if (!(b.lit >> i & 1u)) continue;
                    const Vec3f c = (b.n[i] + Vec3f(1, 1, 1)) * 0.5f;
                    if (params_.highlight.empty()) {
                        store(b, i, c);
                    } else {
                        store(b, i, (b.marked >> i & 1u) ? highlighted(c) : ghosted(c));
                    }
                }
                return;
            case Shading::Headlight:
                for (int i = 0; i < P; ++i) {
                    if (b.lit >> i & 1u) store(b, i, b.colour[i] * shading::headlight(b.n[i], direction(b.ray[i])));
                }
                return;
            case Shading::Sun: {
                const std::uint32_t visible = sunlit(b, lane, rays);
                for (int i = 0; i < P; ++i) {
                    if (!(b.lit >> i & 1u)) continue;
                    light[i] = shading::sun(dot(b.n[i], sun_), (visible >> i & 1u) ? 1.0f : 0.0f);
                    store(b, i, b.colour[i] * light[i]);
                }
                return;
            }
            case Shading::AmbientOcclusion:
                ambient_occlusion(b, lane, rays, light);
                for (int i = 0; i < P; ++i) {
                    if (b.lit >> i & 1u) store(b, i, b.colour[i] * light[i]);
                }
                return;
            case Shading::Indirect:
                indirect(b, lane, rays);
                return;
        }
    }

    template <int P>
    void store(const Block<P>& b, int i, const Vec3f& colour) const {
        shading::store_rgb(colour, frame_.rgb.data() + 3 * pixel(b.x[i], b.y[i]));
    }

    // Occlusion of up to P rays sharing an origin or a direction, in packets the backend
    // can use: 16, 8 or 4 rays, or one.
    template <int P>
    std::uint32_t occluded(Lane& lane, const Secondary* rays, std::uint32_t mask, RayGroup group) const {
        if (!mask) return 0;
        if constexpr (P >= 16) {
            std::uint32_t out = 0;
            for (int i = 0; i < P; i += 16) {
                out |= backend_.template occluded<16>(lane, rays + i, (mask >> i) & 0xffffu, group) << i;
            }
            return out;
        } else if constexpr (P >= 4) {
            return backend_.template occluded<P>(lane, rays, mask, group);
        } else {
            std::uint32_t out = 0;
            for (int i = 0; i < P; ++i) {
                if (mask >> i & 1u) out |= backend_.template occluded<1>(lane, rays + i, 1u, group) << i;
            }
            return out;
        }
    }

    // The pixels of the block that see the sun (facing it, and no shadow ray blocked).
    template <int P>
    std::uint32_t sunlit(const Block<P>& b, Lane& lane, LaneRays& rays) const {
        Secondary shadow[P];
        std::uint32_t facing = 0;
        const float inf = std::numeric_limits<float>::infinity();
        for (int i = 0; i < P; ++i) {
            if (!(b.lit >> i & 1u) || !(dot(b.n[i], sun_) > 0)) {
                shadow[i] = Secondary{};
                continue;
            }
            facing |= 1u << i;
            shadow[i] = backend_.secondary_ray(b.ray[i], b.hit[i], b.n[i], sun_, inf, SecondaryRay::Shadow);
        }
        rays.secondary += static_cast<std::uint64_t>(__builtin_popcount(facing));
        std::uint32_t query = facing;
        for (int i = 0; i < P; ++i) {
            if ((query >> i & 1u) && !clip_secondary(shadow[i])) query &= ~(1u << i);  // all on the cut side
        }
        return facing & ~occluded<P>(lane, shadow, query, RayGroup::SharedDirection);
    }

    // The ambient light of the block's lit pixels (light[i]): `ao_samples` rays each, in
    // queries of 8 that share an origin, handed to the backend 16 at a time so that it
    // can keep several in flight (occluded_group).
    template <int P>
    void ambient_occlusion(const Block<P>& b, Lane& lane, LaneRays& rays, float* light) const {
        constexpr int kGroup = 8;     // AO rays of one pixel per occlusion query
        constexpr int kQueries = 16;  // queries per occluded_group call
        const int samples = std::max(1, params_.ao_samples);
        const int first = params_.sample_index * samples;
        Secondary probe[kQueries][kGroup];
        const Secondary* query[kQueries];
        std::uint32_t mask[kQueries], blocked[kQueries];
        int pixel_of[kQueries];
        int open[P] = {};
        int q = 0;
        auto flush = [&]() {
            backend_.template occluded_group<kGroup>(lane, query, mask, blocked, q, RayGroup::SharedOrigin);
            for (int j = 0; j < q; ++j) open[pixel_of[j]] -= __builtin_popcount(blocked[j]);
            q = 0;
        };
        for (int i = 0; i < P; ++i) {
            if (!(b.lit >> i & 1u)) continue;
            open[i] = samples;  // less the blocked rays (a ray cut away by a section is open)
            const shading::Basis basis(b.n[i]);
            for (int k0 = 0; k0 < samples; k0 += kGroup) {
                Secondary* p = probe[q];
                const int count = std::min(kGroup, samples - k0);
                for (int k = 0; k < count; ++k) {
                    const Vec3f dir = shading::ao_direction(basis, b.x[i], b.y[i], first + k0 + k);
                    p[k] = backend_.secondary_ray(b.ray[i], b.hit[i], b.n[i], dir, backend_.ao_distance(),
                                                  SecondaryRay::AmbientOcclusion);
                }
                for (int k = count; k < kGroup; ++k) p[k] = p[0];
                std::uint32_t m = (1u << count) - 1;
                for (int k = 0; k < count; ++k) {
                    if (!clip_secondary(p[k])) m &= ~(1u << k);  // cut away: open
                }
                query[q] = p;
                mask[q] = m;
                pixel_of[q] = i;
                if (++q == kQueries) flush();
            }
            rays.secondary += static_cast<std::uint64_t>(samples);
        }
        if (q > 0) flush();
        for (int i = 0; i < P; ++i) {
            if (b.lit >> i & 1u) light[i] = shading::ambient(open[i], samples);
        }
    }

    // Sun with shadows, plus one bounce: kDiffuseRays cosine-weighted rays per pixel
    // bring the sky's light where they escape and the sunlit surface's where they hit
    // (a shadow ray from that surface). The noisy part (the diffuse rays' light) waits
    // in `indirect_` for the filter; compose() makes the pixel.
    template <int P>
    void indirect(const Block<P>& b, Lane& lane, LaneRays& rays) const {
        constexpr int D = shading::kDiffuseRays;
        const std::uint32_t visible = sunlit(b, lane, rays);
        Secondary diffuse[P * D];
        Hit bounce[P * D];
        Vec3f bounce_light[P * D];
        Secondary shadow[P * D];
        std::uint32_t facing[(P * D + 31) / 32] = {};
        const float inf = std::numeric_limits<float>::infinity();
        // The block's diffuse rays go to the backend together, which may trace those that
        // agree in direction as packets.
        static_assert(P * D <= 32, "diffuse rays per block are a 32-bit mask");
        std::uint32_t traced = 0;
        for (int i = 0; i < P; ++i) {
            if (!(b.lit >> i & 1u)) continue;
            const shading::Basis basis(b.n[i]);
            for (int k = 0; k < D; ++k) {
                const int j = D * i + k;
                const Vec3f dir = shading::ao_direction(basis, b.x[i], b.y[i], D * params_.sample_index + k,
                                                        shading::kDiffuseSalt);
                diffuse[j] = backend_.secondary_ray(b.ray[i], b.hit[i], b.n[i], dir, inf, SecondaryRay::Diffuse);
                bounce[j].prim = kNoHit;  // stays so when cut away: it sees the sky
                if (clip_secondary(diffuse[j])) traced |= 1u << j;
            }
        }
        backend_.template trace_secondary<P * D>(lane, diffuse, bounce, traced);
        for (int i = 0; i < P; ++i) {
            if (!(b.lit >> i & 1u)) continue;
            for (int k = 0; k < D; ++k) {
                const int j = D * i + k;
                const Vec3f& dir = direction(diffuse[j].ray);
                ++rays.secondary;
                if (bounce[j].prim == kNoHit) {
                    bounce_light[j] = shading::sky(dir, up_);
                    continue;
                }
                Vec3f ny, albedo;
                backend_.surface(bounce[j], ny, albedo);
                if (dot(ny, dir) > 0) ny = -ny;  // the side the diffuse ray sees
                const float lambert = dot(ny, sun_);
                bounce_light[j] = albedo * (shading::kSunLight * std::max(0.0f, lambert));
                if (lambert > 0) {
                    shadow[j] = backend_.secondary_ray(diffuse[j].ray, bounce[j], ny, sun_, inf, SecondaryRay::Shadow);
                    if (clip_secondary(shadow[j])) facing[j / 32] |= 1u << (j % 32);
                }
            }
        }
        // The bounce points' shadow rays share the sun's direction.
        for (int g = 0; g < (P * D + 31) / 32; ++g) {
            if (!facing[g]) continue;
            rays.secondary += static_cast<std::uint64_t>(__builtin_popcount(facing[g]));
            constexpr int G = P * D >= 32 ? 32 : P * D;
            const std::uint32_t blocked = occluded<G>(lane, shadow + 32 * g, facing[g], RayGroup::SharedDirection);
            for (int j = 0; j < G; ++j) {
                if (blocked >> j & 1u) bounce_light[32 * g + j] = Vec3f(0, 0, 0);
            }
        }
        for (int i = 0; i < P; ++i) {
            if (!(b.lit >> i & 1u)) continue;
            const std::size_t px = pixel(b.x[i], b.y[i]);
            Vec3f sum(0, 0, 0);
            for (int k = 0; k < D; ++k) sum += bounce_light[D * i + k];
            const Vec3f mean = sum * (1.0f / static_cast<float>(D));
            const float direct = (visible >> i & 1u) ? shading::kSunLight * dot(b.n[i], sun_) : 0.0f;
            for (int c = 0; c < 3; ++c) {
                indirect_->albedo[3 * px + c] = b.colour[i][c];
                indirect_->light[3 * px + c] = mean[c];
                indirect_->normal[3 * px + c] = b.n[i][c];
            }
            indirect_->direct[px] = direct;
        }
    }

    static const Vec3f& direction(const vastray::Ray& r) { return r.dir; }
    static const Vec3f& origin(const vastray::Ray& r) { return r.org; }
    template <typename R>
    static const Vec3f& origin(const R& r) {
        return r.ray.org;
    }
    template <typename R>
    static const Vec3f& direction(const R& r) {
        return r.ray.dir;
    }
    static vastray::Ray& base(vastray::Ray& r) { return r; }
    template <typename R>
    static vastray::Ray& base(R& r) {
        return r.ray;
    }

    const Backend& backend_;
    const RenderParams& params_;
    int packets_;
    Frame& frame_;
    IndirectTerms* indirect_;
    const LocalSections& sections_;
    Vec3f sun_, up_;
    bool cull_tiles_ = false;   // the model's box is finite: may_enter_model can test tiles against it
    bool orthographic_ = false;  // parallel primary rays (may_enter_model_parallel)
    Vec3d first_origin_;        // pixel (0, 0)'s ray origin: the eye, in perspective
    Vec3d to_corner_[8];        // the box's corners from first_origin_
    double corner_slack_[8];    // how far beyond a side each must lie for the test to count it
};

// The indirect mode's pixels once every pixel is traced: the diffuse light filtered,
// then albedo * (sun + filtered light).
inline void compose_indirect(IndirectTerms& terms, const shading::CameraRays& camera, const RenderParams& params,
                             Frame& frame) {
    denoise::Guides guides;
    guides.width = frame.width;
    guides.height = frame.height;
    guides.depth = frame.depth.data();
    guides.normal = terms.normal.data();
    guides.pixel_angle = static_cast<float>(camera.pixel_angle);
    if (camera.orthographic) guides.pixel_size = static_cast<float>(camera.pixel_size);
    denoise::filter(guides, terms.light, params.threads);
    const std::size_t pixels = frame.depth.size();
    for (std::size_t p = 0; p < pixels; ++p) {
        if (!(frame.depth[p] < std::numeric_limits<float>::infinity()) || frame.prim[p] == kPrimCap) continue;
        Vec3f c;
        for (int k = 0; k < 3; ++k) c[k] = terms.albedo[3 * p + k] * (terms.direct[p] + terms.light[3 * p + k]);
        shading::store_rgb(c, frame.rgb.data() + 3 * p);
    }
}

// Renders every tile of `frame` (already sized and blank) with `backend`, one Lane per
// pool lane, and adds the ray counts to frame.stats. `lanes` stays with the caller,
// which may have more to collect from it (the out-of-core renderer's block requests).
template <typename Backend>
void trace_frame(const Backend& backend, const Camera& camera, const RenderParams& params, int packets,
                 std::vector<typename Backend::Lane>& lanes, Frame& frame) {
    std::unique_ptr<IndirectTerms> terms;
    if (params.shading == Shading::Indirect) terms = std::make_unique<IndirectTerms>(frame.depth.size());
    const LocalSections sections(params.sections, backend.centre());
    const FrameShader<Backend> shader(backend, params, camera, packets, frame, terms.get(), sections);
    std::vector<LaneRays> rays(lanes.size());
    shading::for_each_tile(camera, params, [&](int x0, int y0, int x1, int y1, unsigned lane) {
        shader.render_tile(x0, y0, x1, y1, lanes[lane], rays[lane]);
    });
    if (terms) compose_indirect(*terms, shading::CameraRays(camera), params, frame);
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

VASTRAY_KERNEL_END
