// Writes the out-of-core model format (docs/FORMAT.md): turns kd-subtrees into treelets
// with LOD voxels, packs them into 64 KB blocks per LOD level and packs leaf triangles
// into triangle blocks with shared vertices.
//
// The tree is written bottom-up. A treelet is finished only when everything below it
// is, so its LOD nodes know where their child treelets went and their voxels can be
// sampled from the finished level below. A finished treelet stays pending (in memory)
// until its parent places it next to its sibling: the two children of a LOD node must
// share a block, because the node stores one block id. Only the treelets along the
// current path are pending, so memory stays bounded by the subtree being built.
//
// The caller (vastray.build) owns the top of the tree: it splits out of core with
// temp files, hands each subtree that fits in memory to add_subtree(), then describes
// the out-of-core treelets above them with add_inner_treelet().
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <vector>

#include "vastray/format.h"
#include "vastray/kdtree.h"

namespace vastray {

struct ModelWriterParams {
    KdBuildParams kd;
    bool has_colours = false;
    int voxel_rays_per_axis = 3;        // a k x k grid of rays per voxel face
    float one_sample_colour = 0.05f;    // six samples collapse to one when every colour
    float one_sample_normal = 0.10f;    // and normal component is this close to the mean
    // FLAG_QUANTIZED_VERTICES: the records' vertices are on the root cell's grid with
    // these steps (format.h), and triangle blocks store them as bit-packed grid offsets.
    bool quantized_vertices = false;
    Vec3f vertex_steps{1, 1, 1};
    // FLAG_TIERED (writer/tiers.h): each level's units go to streams by the radius of
    // the LOD node above them, a tier per `tier_width` halvings below R_root / 2^
    // `tier_coarse_octaves`, which is tier 0. Width 0: one stream per level.
    double tier_width = 0;
    int tier_coarse_octaves = 4;
    float root_radius = 0;  // half the root cell's diagonal (format::cell_radius)
    // FLAG_COMPACT_TRIANGLES: triangle blocks in the compact layout (format.h).
    bool compact_triangles = false;
    // Six-sample voxels that show at most two colours in four words (format version 6,
    // format::pack_voxel): the same samples, 8 bytes fewer. Off writes six words, as
    // version 5 did (for comparisons).
    bool packed_voxels = true;
    // With quantized splits: treelets on 4-byte boundaries and LOD words in 4-byte units
    // (format version 7, FLAG_PACKED_TREELETS). Off pads them to 8 bytes, as version 6
    // did (for comparisons and older-version tests).
    bool packed_treelets = true;
    // With quantized splits: LOD nodes carry a surface error (format version 8,
    // FLAG_VOXEL_ERRORS; writer/voxel_errors.h), which their LOD test compares instead of
    // the radius R, never below `voxel_error_floor` * R (0 ... 1; 1 keeps the radius, so
    // that no voxel is taken while it covers more than the PoE allows a voxel's size).
    bool voxel_errors = false;
    float voxel_error_floor = 0.5f;
    // Blocks compressed with LZ4 HC at this level (1 ... 12) instead of the fast
    // compressor (0): the same format and decoding, smaller blocks, a slower build.
    int lz4_hc_level = 0;
};

// What one stream of a level holds: its blocks and their raw bytes; nodes and LOD voxels
// (node levels) or triangle records and vertices (the triangle level), as the level
// table counts them (docs/FORMAT.md §5).
struct StreamStats {
    std::uint64_t blocks = 0, bytes = 0, items = 0, extra = 0;
    StreamStats& operator+=(const StreamStats& o) {
        blocks += o.blocks;
        bytes += o.bytes;
        items += o.items;
        extra += o.extra;
        return *this;
    }
};

struct ModelWriterStats {
    std::uint64_t basic_nodes = 0, lod_nodes = 0, leaves = 0, empty_children = 0;
    std::uint64_t voxels_one = 0, voxels_six = 0, treelets = 0;
    std::uint64_t voxels_packed = 0;  // six-sample voxels in the packed form (4 words), among voxels_six
    // FLAG_VOXEL_ERRORS: LOD nodes whose error is below their radius, the sum of error /
    // radius over all LOD nodes, and the time the errors took (in emit_ms too).
    std::uint64_t lod_errors_below_radius = 0;
    double lod_error_ratio_sum = 0, voxel_error_ms = 0;
    std::uint64_t references = 0;           // leaf triangle-list entries
    std::uint64_t stored_triangles = 0;     // triangle records (a triangle repeats across blocks)
    std::uint64_t stored_vertices = 0;
    std::uint64_t degenerate = 0;           // zero-area triangles left out
    std::uint64_t triangle_blocks = 0;
    std::uint64_t vertex_bytes = 0;  // raw bytes of the triangle blocks' vertex sections
    std::vector<std::vector<StreamStats>> node_streams;  // [level][tier]
    std::vector<StreamStats> triangle_streams;           // [tier]
    std::uint64_t triangle_bytes = 0;       // raw bytes of the triangle blocks
    double kd_build_ms = 0, emit_ms = 0;
    int max_depth = 0;
    std::uint64_t emission_jobs = 0;  // subtrees emitted in parallel and merged (parallel_emission.h)
};

// A finished block as the file stores it (docs/FORMAT.md §6): LZ4-compressed unless
// that does not make it smaller, with the CRC-32 of the stored bytes.
struct StoredBlock {
    std::vector<std::uint8_t> bytes;
    std::uint32_t raw_size = 0, crc32 = 0, codec = 0;
};
// Compresses and checksums one raw block.
// LZ4-compressed (hc_level 0: the fast compressor; 1 ... 12: LZ4 HC), or stored raw
// where that would not shrink it.
StoredBlock store_block(const std::vector<std::uint8_t>& raw, int hc_level = 0);

// Receives each finished block, in the order of its stream (a level's tier): level >= 0
// is a node level, -1 the triangle level. Blocks of parts emitted in parallel are
// compressed on the threads that made them; the sink is called from one thread at a time.
using BlockSink = std::function<void(int level, std::uint32_t tier, StoredBlock&& block)>;
// Reports leaf triangle references written so far (for progress bars).
using ProgressSink = std::function<void(std::uint64_t references)>;

// Bytes of one builder record (vastray/build.py writes them).
inline std::size_t record_size(bool has_colours) { return 36 + 4 + (has_colours ? 4 : 0); }

class ModelWriter {
public:
    ModelWriter(const ModelWriterParams& params, BlockSink sink, ProgressSink progress);
    ~ModelWriter();
    ModelWriter(const ModelWriter&) = delete;
    ModelWriter& operator=(const ModelWriter&) = delete;

    // Builds a kd-tree over n triangle records (record_size bytes each: nine f32 corners,
    // model-local; the u32 input id; the u32 colour 0x00BBGGRR when the model has
    // colours) inside `cell`, whose root sits at depth 3 * level, and writes all of it
    // except its root treelet, which stays pending under the returned handle. The
    // records are read in place (no copy) until the call returns. `lod_parent`: the cell
    // of the LOD node above the subtree's root (in the out-of-core treelet that will be
    // added over it), whose radius is the tier key of the root treelet's leaves; null
    // for the model's root.
    int add_subtree(const std::uint8_t* records, std::size_t stride, std::size_t n, const Box3f& cell, int level,
                    const Box3f* lod_parent = nullptr);

    // A treelet of three median-split levels above eight pending children. Nodes are in
    // heap order (0 root, 1-2 its children, 3-6 grandchildren); child slot 2j + s
    // belongs to grandchild j (s = 0 below the split). Handle -1: empty child.
    int add_inner_treelet(int level, const Box3f& cell, const std::array<int, 7>& axes,
                          const std::array<float, 7>& splits, const std::array<int, 8>& children);

    // Writes the root treelet into level 0 and flushes every partly filled block.
    void finish(int root);

    const ModelWriterStats& stats() const { return stats_; }

    struct Impl;

private:
    std::unique_ptr<Impl> impl_;
    ModelWriterStats& stats_;
};

}  // namespace vastray
