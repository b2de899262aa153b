// Emission of an in-core kd-subtree as treelets, LOD voxels and triangle blocks, and
// the merge that keeps the file independent of how many threads emitted it.
//
// The writer has a main emitter that feeds the model's sink. Parts of a subtree emitted
// in parallel get their own emitters, which defer placing treelets (they record
// placement units instead) and buffer their triangle blocks; the main emitter merges
// them in tree order, packing the units into its own blocks, so nodes pack exactly as
// if one thread had emitted everything. Every unit goes to the stream of its level's
// coarseness tier (tiers.h); each stream has its own block ids.
#pragma once

#include <cstddef>
#include <cstdint>
#include <deque>
#include <functional>
#include <mutex>
#include <vector>

#include "vastray/kdtree.h"
#include "vastray/model_writer.h"
#include "writer/block_stream.h"
#include "writer/node_blocks.h"
#include "writer/tiers.h"
#include "writer/treelet.h"
#include "writer/triangle_blocks.h"

namespace vastray::writer {

// Leaf references written so far, shared by the emitters of one writer (progress bars).
struct ProgressCounter {
    ProgressSink sink;
    std::mutex mutex;
    std::uint64_t references = 0, reported = 0;

    void add(std::uint64_t n);
};

// Sibling treelets a deferred emitter would have placed in a block of stream
// (`level`, `tier`).
struct Unit {
    std::size_t level;
    std::uint32_t tier;
    Pending data;
};

// A finished triangle block of a deferred emitter, with its tier.
struct BufferedBlock {
    std::uint32_t tier;
    StoredBlock block;
};

class SubtreeEmitter {
public:
    SubtreeEmitter(const ModelWriterParams& params, ProgressCounter& counter, BlockStream out, bool defer);

    // The part whose kd-tree is being emitted (kept by the caller meanwhile), and the
    // surface errors of its nodes (kd_errors; null when the model keeps none).
    void bind(const KdTree* tree, const TriangleSource& source, const float* errors = nullptr) {
        tree_ = tree;
        src_ = source;
        errors_ = errors;
    }
    const float* errors() const { return errors_; }

    // Emits the treelet rooted at kd node `root` and everything below it; `tier` is the
    // tier of its leaves (that of the LOD node above it). `jobs`, when given, is asked
    // for each child treelet first: it returns true (and the child's root treelet) when
    // that subtree was emitted elsewhere and is now merged into this one.
    using JobLookup = std::function<bool(std::uint32_t kd_node, Pending& root)>;
    Pending emit_kd_treelet(std::uint32_t root, const Box3f& cell, std::size_t level, std::uint32_t tier,
                            const JobLookup* jobs = nullptr);

    // Finishes a LOD node whose children are finished: samples its voxel, places the
    // children side by side one level down (or records them as a unit when deferring),
    // and records where they went.
    void finish_lod(TreeletNode& node, Pending* a, Pending* b, std::size_t level, Pending& self);

    // Lays out a finished treelet into `out`.
    void serialise(std::vector<TreeletNode>& treelet, Pending& out) {
        serialise_treelet(treelet, stats, out, p_.kd.quantized_splits, packed_treelets(), voxel_errors());
    }
    // FLAG_PACKED_TREELETS: with quantized splits only (their nodes are multiples of 4).
    bool packed_treelets() const { return p_.kd.quantized_splits && p_.packed_treelets; }
    // FLAG_VOXEL_ERRORS: likewise (a LOD node's split goes in as a step).
    bool voxel_errors() const { return p_.kd.quantized_splits && p_.voxel_errors; }

    // Sets the error code of a LOD node whose `error` (its cell's surface error) is set.
    void code_error(TreeletNode& lod) const;
    // What a LOD node's test compares: its coded error, or its radius without errors.
    float lod_key(const TreeletNode& lod) const;

    // The tier of the units below a LOD node: by its key (the error a ray refuses before
    // it needs them).
    std::uint32_t tier_below(const TreeletNode& lod) const { return tiering_.tier_of(lod_key(lod)); }
    // The tier of the units below a part's root, by the radius of the LOD node above it
    // (`cell`), whose error is not known while the part is emitted: a tier no finer.
    std::uint32_t tier_below(const Box3f& cell) const { return tiering_.tier_of(format::cell_radius(cell.extent())); }
    const Tiering& tiering() const { return tiering_; }

    // Ends a deferring emitter's part: keeps the leaves of each tier's open block for the
    // merge (take_open_leaves) and drops the per-tier packers.
    void finish_deferred();

    // Moves a part emitted in parallel into these streams. Per tier, its closed
    // triangle blocks follow ours (their ids become base + id; our open block is closed
    // first when it has some), and the leaves of its last, open block join our open
    // block. Its placement units are packed into our node blocks in the order the part
    // made them, children before parents, so each LOD node learns its children's block
    // and offset before it is placed itself. `root` is the part's root treelet, whose
    // ids are resolved too.
    void merge(SubtreeEmitter& part, std::vector<BufferedBlock>& triangle_blocks, Pending& root);

private:
    // A stream's block id as nodes store it; throws when a tiered stream outgrows its bits.
    std::uint32_t reference(std::uint32_t tier, std::uint32_t block) const;

    const ModelWriterParams& p_;
    ProgressCounter& counter_;
    BlockStream out_;
    RawBlockStream pack_;  // compresses into out_; declared before the block packers that write into it
    bool defer_;
    Tiering tiering_;
    std::vector<Unit> units_;
    // A finished deferring emitter: per tier, its closed blocks and its open block's leaves.
    std::vector<std::uint32_t> closed_;
    std::vector<std::vector<OpenLeaf>> open_leaves_;
    std::deque<std::vector<TreeletNode>> treelets_;  // by depth of emit_kd_treelet; a deque keeps them in place
    std::size_t depth_ = 0;
    static constexpr std::uint64_t kProgressBatch = 1 << 14;
    std::uint64_t unreported_ = 0;  // leaf references not yet added to counter_
    const KdTree* tree_ = nullptr;
    TriangleSource src_;
    const float* errors_ = nullptr;

public:
    ModelWriterStats stats;
    NodeBlocks nodes;
    TriangleTiers triangles;
};

}  // namespace vastray::writer
