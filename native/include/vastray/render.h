// The camera, the render parameters and the frame: what both renderers take and give.
// The in-core renderer (render.cpp, a Scene) and the out-of-core LOD renderer
// (lod_render.cpp, a model in a block cache) share one parameter struct, one stats
// struct and one frame loop (frame_renderer.h); only their traversals differ.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "vastray/frame_stats.h"
#include "vastray/scene.h"

namespace vastray {

struct Camera {
    Vec3d eye, target, up{0, 1, 0};
    double fov_deg = 45;  // vertical field of view
    int width = 640, height = 480;
    // Orthographic: every pixel looks along the view, and the image spans what the
    // perspective one spans at the target (2 |target - eye| tan(fov/2) high), so
    // switching keeps the target's scale and moving the eye closer still zooms in. The
    // rays start behind the model (CameraRays::start_behind): nothing is cut off by the
    // eye, as CAD viewers' parallel views cut nothing.
    bool orthographic = false;

    // Throws std::invalid_argument with a readable reason for absurd values
    // (NaN, eye == target, up parallel to the view, fov outside (0, 180), empty image).
    void validate() const;
};

constexpr int kMaxImageSide = 16384;

// normal: false colour of the normal; headlight: diffuse from the eye; sun: directional
// light with shadow rays; ao: ambient occlusion; indirect: sun with shadows, one bounce
// of indirect light and a hemispherical sky, two diffuse rays per pixel, denoised by an
// edge-aware filter (paper 000 Fig. 1, Table 5).
enum class Shading { Normal, Headlight, Sun, AmbientOcclusion, Indirect };
Shading parse_shading(const std::string& name);
const char* shading_name(Shading shading);
// Whether the mode traces any-hit (shadow, AO) rays: in core they walk the scene's 8-wide BVH.
bool traces_any_hit_rays(Shading shading);

// Which structures the in-core scene's rays walk, decided without building anything: its
// wide BVH, unless VASTRAY_PRIMARY=kd (closest-hit rays: a frame's primary rays and the
// batch query) or VASTRAY_ANYHIT=kd (any-hit rays, and the indirect mode's diffuse rays)
// ask for the kd-tree, or the scene is too large for the wide BVH. One rule for the
// renderer, which builds what a frame walks before the frame, and for the tools that
// build and report the same ahead (the CLI). A VASTRAY_PRIMARY other than kd or wide
// throws std::invalid_argument.
bool closest_hits_walk_wide_bvh(const Scene& scene);
bool any_hits_walk_wide_bvh(const Scene& scene);
struct FrameStructures {
    bool primary_wide = false;    // the primary rays walk the wide BVH (else the kd-tree)
    bool secondary = false;       // the mode traces secondary rays
    bool secondary_wide = false;  // they walk the wide BVH (else the kd-tree)
    bool wide() const { return primary_wide || (secondary && secondary_wide); }
    bool kd() const { return !primary_wide || (secondary && !secondary_wide); }
};
FrameStructures frame_structures(const Scene& scene, Shading shading);

// A section (clipping) plane in world coordinates: geometry where dot(normal, p) +
// offset < 0 is cut away. Where a ray enters a solid through the cut it sees a cap.
struct SectionPlane {
    Vec3d normal;
    double offset = 0;
};
constexpr std::size_t kMaxSectionPlanes = 6;
// Throws std::invalid_argument for a zero or non-finite normal or offset, or too many.
void validate_sections(const std::vector<SectionPlane>& planes);

// A run of input triangle ids [first, end): how a highlight set reaches the renderer (a
// part is one or more runs; vastray/parts.py turns part ids into runs).
struct TriangleRange {
    std::uint32_t first = 0, end = 0;
};
constexpr std::size_t kMaxHighlightRanges = std::size_t{1} << 22;
// Throws std::invalid_argument unless the runs are non-empty, sorted and disjoint.
void validate_highlight(const std::vector<TriangleRange>& ranges);
// Whether input triangle `prim` lies in one of the sorted runs.
inline bool in_ranges(const std::vector<TriangleRange>& ranges, std::int32_t prim) {
    if (prim < 0 || ranges.empty()) return false;
    const auto id = static_cast<std::uint32_t>(prim);
    std::size_t lo = 0, hi = ranges.size();  // first run whose end lies past id
    while (lo < hi) {
        const std::size_t mid = (lo + hi) / 2;
        if (ranges[mid].end <= id) lo = mid + 1; else hi = mid;
    }
    return lo < ranges.size() && ranges[lo].first <= id;
}

struct RenderParams {
    Shading shading = Shading::Headlight;
    int ao_samples = 8;
    double ao_distance = 0;  // 0: a fifth of the model's diagonal
    Vec3d sun_direction{0.35, 0.8, 0.5};  // towards the sun, world frame
    unsigned threads = 0;                  // 0: every lane of the pool
    int tile_size = 16;
    // Primary rays per packet: 16 (4x4 blocks), 4 (2x2 quads), 1 (single rays), or 0
    // for each renderer's fastest: 4x4 SIMD packets in core and out of core (out of core
    // they pay even where rays part and most steps have one active lane;
    // bench/results/tradeoff-size.md). Secondary rays go in packets whatever this says.
    int packets = 0;
    // Level of detail (out of core; an in-core scene always renders full detail).
    // Pixels of error: a voxel may stand in for its subtree once its projected
    // diameter is at most this many pixels. 0 is full detail.
    double pixels_of_error = 1;
    // Solid-angle metric for AO and diffuse rays, in steradians; negative: derived from
    // the PoE.
    double solid_angle = -1;
    // Which pass of a still view this frame is: pass k draws other random numbers (AO
    // and diffuse directions) than passes 0 .. k-1, so averaging the images of passes
    // 0 .. K-1 gives K times the samples (see average_passes in vastray/renderer.py).
    int sample_index = 0;
    // Out of core: the most blocks this frame may add to the fetch queue; 0 is the
    // cache's bound (max_requests_per_frame). Full-detail mode raises it, as it waits
    // for the data anyway.
    int request_limit = 0;
    // Section planes (at most kMaxSectionPlanes): rays, primary and secondary, see only
    // what lies on the kept side of every plane.
    std::vector<SectionPlane> sections;
    // Highlighted triangles (sorted, disjoint runs of input triangle ids): their surface
    // colour is blended towards the highlight colour in every shading mode. A LOD voxel
    // stands for many triangles and is never highlighted.
    std::vector<TriangleRange> highlight;

    // Throws std::invalid_argument naming the field and its allowed range.
    void validate() const;
    int packets_or(int fastest) const { return packets == 0 ? fastest : packets; }
};

// An allocator whose resize() leaves new elements uninitialised: a frame's buffers are
// written in full by the threads that draw it (shading::blank_frame), not first cleared
// by one thread, which also took every page fault of 10 MB of fresh memory per 720p frame.
template <typename T>
struct UninitialisedAllocator : std::allocator<T> {
    template <typename U>
    struct rebind {
        using other = UninitialisedAllocator<U>;
    };
    UninitialisedAllocator() = default;
    template <typename U>
    UninitialisedAllocator(const UninitialisedAllocator<U>&) noexcept {}
    template <typename U, typename... Args>
    void construct(U* p, Args&&... args) {
        if constexpr (sizeof...(Args) == 0) {
            ::new (static_cast<void*>(p)) U;
        } else {
            ::new (static_cast<void*>(p)) U(std::forward<Args>(args)...);
        }
    }
};
template <typename T>
using PixelBuffer = std::vector<T, UninitialisedAllocator<T>>;

struct Frame {
    int width = 0, height = 0;
    PixelBuffer<std::uint8_t> rgb;     // height * width * 3
    PixelBuffer<float> depth;          // distance along the unit view ray; inf on a miss
    PixelBuffer<std::int32_t> prim;    // input triangle id; -1 on a miss, -2 on a LOD voxel
    FrameStats stats;
};

// Frame::prim where a pixel sees nothing, a LOD voxel, or the cap of a cut solid.
constexpr std::int32_t kPrimBackground = -1, kPrimVoxel = -2, kPrimCap = -3;

Frame render(const Scene& scene, const Camera& camera, const RenderParams& params);

}  // namespace vastray
