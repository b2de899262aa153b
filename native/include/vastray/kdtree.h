// In-core kd-tree over triangles: binned SAH with empty-space cutting (paper 000 §4.1).
//
// Node layout: 8 bytes, the same size as the out-of-core basic/leaf nodes (paper 000
// Tables 2 and 4), so the traversal loop is shared once treelets arrive. Nodes are in
// depth-first preorder: an inner node's left (below) child follows it directly and
// the right (above) child sits at a positive offset. Offsets are relative, so subtrees
// built in parallel are spliced together without rewriting inner nodes.
#pragma once

#include <cstdint>
#include <cstring>
#include <vector>

#include "vastray/huge_pages.h"
#include "vastray/vecmath.h"

namespace vastray {

struct KdNode {
    // inner: bits 0-1 split axis (0, 1, 2); bit 2 left child empty; bit 3 right child
    //        empty; bits 4-31 offset of the right child from this node. Empty children
    //        are not stored (paper 000 Table 2's empty flags): an empty left child puts
    //        the right one directly after its parent, and the traversal never visits
    //        either kind, which matters because empty-space cutting makes many.
    // leaf:  bits 0-1 = 3; bits 2-31 triangle count.
    std::uint32_t bits;
    // inner: split position (float bits); leaf: first index in the triangle-id list.
    std::uint32_t payload;

    static constexpr std::uint32_t kLeaf = 3;
    static constexpr std::uint32_t kLeftEmpty = 4, kRightEmpty = 8;
    static constexpr std::uint32_t kMaxCount = (1u << 30) - 1;
    static constexpr std::uint32_t kMaxOffset = (1u << 28) - 1;

    bool is_leaf() const { return (bits & 3u) == kLeaf; }
    int axis() const { return static_cast<int>(bits & 3u); }
    bool left_empty() const { return (bits & kLeftEmpty) != 0; }
    bool right_empty() const { return (bits & kRightEmpty) != 0; }
    std::uint32_t right_offset() const { return bits >> 4; }
    std::uint32_t count() const { return bits >> 2; }
    std::uint32_t first() const { return payload; }
    float split() const {
        float f;
        std::memcpy(&f, &payload, sizeof f);
        return f;
    }

    static KdNode inner(int axis, float split, std::uint32_t right_offset, std::uint32_t empty_flags) {
        std::uint32_t p;
        std::memcpy(&p, &split, sizeof p);
        return {(right_offset << 4) | empty_flags | static_cast<std::uint32_t>(axis), p};
    }
    static KdNode leaf(std::uint32_t first, std::uint32_t count) {
        return {(count << 2) | kLeaf, first};
    }
};
static_assert(sizeof(KdNode) == 8, "kd-tree nodes are 8 bytes");

struct KdBuildParams {
    // SAH cost of one inner-node step. A step costs more than a triangle test: it is a
    // dependent load that misses the caches once the tree outgrows them, and a branch
    // that mispredicts. 4 (against 1) made the 10^6-10^7 trees 2-6x smaller in nodes and
    // 1.2-2.2x in bytes, built 1.5-2.9x faster, and traced primary, batch and AO rays
    // 1.0-1.26x faster (docs/native-core.md, "kd-tree build").
    float traversal_cost = 4.0f;
    float intersection_cost = 1.5f;  // SAH cost of one triangle test
    int leaf_size = 2;               // nodes with <= this many triangles become leaves
    int bins = 32;                   // SAH candidate planes per axis
    int max_depth = 0;               // 0: 8 + 1.3 log2(n), capped at 60
    float empty_space_ratio = 0.15f; // cut off an empty slab when it holds >= this volume fraction
    int median_fallback = 128;       // SAH found no split but this many triangles remain: split mid
    unsigned threads = 0;            // 0: all hardware threads
    // Every split on the 2^20-step grid of its cell on the split axis (format.h,
    // FLAG_QUANTIZED_SPLITS); the tree is built on those planes, so it stays exact.
    bool quantized_splits = false;
    // The tree's arrays on transparent huge pages (huge_pages.h): for trees that rays walk
    // (a Scene). The model builder's trees live for one part and are written out; there
    // huge pages' cost at each fault (zeroing 2 MiB, compaction) made the kd build of
    // the 10^7 plant 0.74x, so it turns them off.
    bool huge_pages = true;
};

struct KdBuildStats {
    // empty_leaves counts empty children, which are flagged in their parent, not stored.
    std::uint64_t nodes = 0, leaves = 0, empty_leaves = 0, references = 0;
    std::uint64_t degenerate = 0;  // zero-area triangles left out of the tree
    std::uint64_t wide_nodes = 0;  // nodes binned and partitioned by every lane (near the root)
    int max_depth = 0;
    double sah_cost = 0;
    double build_ms = 0;
};

struct KdTree {
    HugeVector<KdNode> nodes;
    HugeVector<std::uint32_t> tri_ids;  // leaf triangle lists
    Box3f bounds;                        // root cell (model-local coordinates)
    KdBuildStats stats;

    std::size_t memory_bytes() const {
        return nodes.size() * sizeof(KdNode) + tri_ids.size() * sizeof(std::uint32_t);
    }
};

// A triangle soup in model-local float coordinates: triangle t's three corners are the
// nine floats at vertices + stride * t (stride 9: packed; more: records with other fields
// after the corners, as the builder's are).
struct TriangleSoup {
    const Vec3f* vertices = nullptr;
    std::size_t count = 0;
    std::size_t stride = 9;  // in floats
    const Vec3f& v(std::size_t tri, int k) const {
        return reinterpret_cast<const Vec3f*>(reinterpret_cast<const float*>(vertices) + stride * tri)[k];
    }
};

// cell: the root cell when the tree is one subtree of a larger one (out-of-core build);
// triangles are clipped to it and those outside it are left out. Null: the triangles' bounds.
KdTree build_kdtree(const TriangleSoup& soup, const KdBuildParams& params, const Box3f* cell = nullptr);

}  // namespace vastray
