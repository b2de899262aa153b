// An 8-wide bounding-volume hierarchy over the in-core triangles, for any-hit rays.
//
// The kd-tree decides one plane per step, so a ray's walk is a chain of ~25 dependent
// node loads before its first leaf; a node of this tree tests a ray against 8 child
// boxes at once (one AVX compare, two SSE ones), about 3 levels of the kd-tree per load.
// That is how Embree answers incoherent occlusion rays (its BVH8), and the AO and shadow
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
    // its triangles being `count` consecutive ones of WideBvh::triangles.
    std::uint32_t child[kWidth];

    static constexpr std::uint32_t kLeafBit = 0x80000000u;
    static constexpr int kCountBits = 3;  // leaves of 1..8 triangles
    static constexpr std::uint32_t kMaxFirst = (kLeafBit >> kCountBits) - 1;

    static bool is_leaf(std::uint32_t c) { return (c & kLeafBit) != 0; }
    static std::uint32_t leaf_first(std::uint32_t c) { return (c & ~kLeafBit) >> kCountBits; }
    static std::uint32_t leaf_count(std::uint32_t c) { return (c & ((1u << kCountBits) - 1)) + 1; }
};
static_assert(sizeof(WideNode) == 256, "a wide node is four cache lines");

// A leaf's triangle: its corners and the scene's index of it (which a secondary ray
// compares with the triangle it starts on), in one record so a leaf is one run of lines.
struct WideTriangle {
    Vec3f v[3];
    std::uint32_t prim;
};
static_assert(sizeof(WideTriangle) == 40, "a wide-BVH triangle is 40 bytes");

struct WideBvh {
    HugeVector<WideNode> nodes;           // nodes[0] is the root
    HugeVector<WideTriangle> triangles;   // in leaf order
    std::uint64_t leaves = 0;
    int max_depth = 0;  // in nodes, the root's children at depth 1
    double build_ms = 0;

    std::size_t memory_bytes() const {
        return nodes.size() * sizeof(WideNode) + triangles.size() * sizeof(WideTriangle);
    }
};

// Binned SAH, children split until eight per node, leaves of at most 2 triangles.
WideBvh build_wide_bvh(const Vec3f* tri_vertices, std::size_t triangle_count, unsigned threads);

}  // namespace vastray
