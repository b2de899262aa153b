// The writer's in-memory form of a treelet (docs/FORMAT.md §7-8): up to seven nodes of
// height 3 as they will be laid out, before and after serialisation.
#pragma once

#include <cstddef>
#include <cstdint>
#include <limits>
#include <vector>

#include "vastray/format.h"
#include "vastray/kdtree.h"
#include "vastray/model_writer.h"
#include "writer/voxel_sampling.h"

namespace vastray::writer {

// A reference that the merge of a part emitted in parallel must resolve. unit < 0: the
// u32 at `offset` is a leaf's triangle block reference local to the part (word 0, its
// first list entry, precedes it). unit >= 0: `offset` is a LOD node whose child
// treelets are the part's placement unit `unit`, not yet in a block.
struct Patch {
    std::uint32_t offset;
    int unit;
};

// A finished treelet waiting for its parent to place it.
struct Pending {
    std::vector<std::uint8_t> bytes;  // the serialised treelet, a multiple of 8 bytes (4 packed)
    std::vector<Proxy> proxies;       // what the LOD node above samples its voxel from
    std::vector<Patch> patches;       // ids to resolve when a parallel part is merged
    std::uint32_t nodes = 0, voxels = 0;  // what the level table counts where it is placed
    // The surface error of the treelet root's cell (voxel_errors.h; infinity when no
    // errors are kept): what an out-of-core treelet above combines its LOD nodes' from.
    float error = std::numeric_limits<float>::infinity();
};

struct TreeletNode {
    enum Kind { Basic, Lod, Leaf } kind = Basic;
    int axis = 0;
    float split = 0;
    Box3f cell;
    std::uint32_t empty = 0;                  // format::kLeftEmpty | format::kRightEmpty
    int left = -1, right = -1;                // basic: indices of the children in the treelet
    std::uint32_t kd_left = 0, kd_right = 0;  // LOD (in-core): kd-tree indices of the children
    int child_handles[2] = {-1, -1};          // LOD (out of core): pending children
    float radius = 0;
    // LOD: the child treelets' block (a block reference), the first one's byte offset in it,
    // and the right one's from the left one.
    std::uint32_t child_block = 0, child_off = 0, right_from_left = 0;
    std::uint32_t voxel[6] = {};  // the voxel's words (format::voxel_words)
    int voxel_words = 0;
    std::uint32_t kd_node = 0;  // (in-core) its kd node
    // The surface error of the cell (voxel_errors.h) and, for a LOD node, the code word 1
    // stores (FLAG_VOXEL_ERRORS).
    float error = std::numeric_limits<float>::infinity();
    std::uint32_t error_code = format::kErrorCodeMax;
    std::uint32_t tri_block = 0, first = 0, count = 0;  // tri_block: a block reference
    int unit = -1;  // LOD (deferred placement): the children's placement unit
    std::size_t offset = 0;
};

inline Box3f child_cell(const Box3f& cell, int axis, float split, int side) {
    Box3f c = cell;
    (side == 0 ? c.hi : c.lo)[axis] = split;
    return c;
}

// The statistics of a stream, grown to hold it.
StreamStats& node_stream(ModelWriterStats& stats, std::size_t level, std::uint32_t tier);
StreamStats& triangle_stream(ModelWriterStats& stats, std::uint32_t tier);

// The nodes of the treelet rooted at kd node `root` (preorder; LOD nodes at depth 2
// keep the kd indices of their children, which root the next level's treelets).
void collect_kd_treelet(const KdTree& tree, std::uint32_t root, const Box3f& cell, std::vector<TreeletNode>& nodes);

// Lays out a finished treelet: nodes in preorder, then the voxels of its LOD nodes, padded
// to 8 bytes. Leaves' triangle block ids are recorded as patches (a parallel part's ids
// are local until it is merged). Counts every node by kind in `stats`, and in `out` the
// nodes and voxels its stream will count. `quantized`: basic nodes take 4 bytes with
// their split as a step of their cell's grid (FLAG_QUANTIZED_SPLITS); a split off that
// grid is a logic error. `packed` (FLAG_PACKED_TREELETS, only with `quantized`): padded
// to 4 bytes instead, with LOD words in 4-byte units.
// `voxel_errors` (FLAG_VOXEL_ERRORS, only with `quantized`): a LOD node's word 1 is its
// split's step and its error code instead of the split in f32.
void serialise_treelet(std::vector<TreeletNode>& nodes, ModelWriterStats& stats, Pending& out, bool quantized = false,
                       bool packed = false, bool voxel_errors = false);


}  // namespace vastray::writer
