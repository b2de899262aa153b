// An 8-wide bounding-volume hierarchy over the in-core triangles, for secondary rays (any
// hit, and the indirect mode's diffuse rays, closest hit).
//
// The kd-tree decides one plane per step, so a ray's walk is a chain of ~25 dependent
// node loads before its first leaf; a node of this tree tests a ray against 8 child
// boxes at once (one AVX compare, two SSE ones), about 3 levels of the kd-tree per load.
// That is how Embree answers incoherent rays (its BVH8), and the AO, shadow and diffuse
// rays of the in-core scene are where the kd-tree lagged it most.
#pragma once

#include <cstddef>
#include <cstdint>

#include "vastray/huge_pages.h"
#include "vastray/vecmath.h"

namespace vastray {

// Children's boxes as structure-of-arrays rows, so one vector load reads a coordinate
// of all eight. An unused slot has an empty box (lo = +inf, hi = -inf): no ray hits it.
struct alignas(64) WideNode {
    static constexpr int kWidth = 8;
    float lo_x[kWidth], hi_x[kWidth], lo_y[kWidth], hi_y[kWidth], lo_z[kWidth], hi_z[kWidth];
    // Inner child: its node index. Leaf: kLeafBit | first << kCountBits | (count - 1),
    // its `count` triangles filling WideQuad::count_for(count) consecutive records of
    // WideBvh::quads from `first`.
    std::uint32_t child[kWidth];

    static constexpr std::uint32_t kLeafBit = 0x80000000u;
    static constexpr int kCountBits = 3;  // leaves of 1..8 triangles
    static constexpr std::uint32_t kMaxFirst = (kLeafBit >> kCountBits) - 1;

    static bool is_leaf(std::uint32_t c) { return (c & kLeafBit) != 0; }
    static std::uint32_t leaf_first(std::uint32_t c) { return (c & ~kLeafBit) >> kCountBits; }
    static std::uint32_t leaf_count(std::uint32_t c) { return (c & ((1u << kCountBits) - 1)) + 1; }
};
static_assert(sizeof(WideNode) == 256, "a wide node is four cache lines");

// A leaf's triangles, up to four to a record with each coordinate of the four side by
// side (v[corner][axis][lane]), so one SSE pass tests them all (wide_traverse.h), and the
// scene's index of each (which a secondary ray compares with the triangle it starts on).
// A leaf of fewer fills its other lanes with copies of its first triangle.
struct alignas(32) WideQuad {
    static constexpr int kLanes = 4;
    float v[3][3][kLanes];
    std::uint32_t prim[kLanes];

    Vec3f corner(int lane, int k) const { return {v[k][0][lane], v[k][1][lane], v[k][2][lane]}; }
    static std::uint32_t count_for(std::uint32_t triangles) { return (triangles + kLanes - 1) / kLanes; }
};
static_assert(sizeof(WideQuad) == 160, "a wide-BVH quad is 160 bytes");

struct WideBvh {
    HugeVector<WideNode> nodes;  // nodes[0] is the root
    HugeVector<WideQuad> quads;  // the leaves' triangles, in leaf order
    std::uint64_t leaves = 0;
    int max_depth = 0;  // in nodes, the root's children at depth 1
    double build_ms = 0;

    std::size_t memory_bytes() const {
        return nodes.size() * sizeof(WideNode) + quads.size() * sizeof(WideQuad);
    }
};

// Binned SAH, children split until eight per node, leaves of at most 4 triangles.
WideBvh build_wide_bvh(const Vec3f* tri_vertices, std::size_t triangle_count, unsigned threads);

}  // namespace vastray
