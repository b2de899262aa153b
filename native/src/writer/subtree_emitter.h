// Emission of an in-core kd-subtree as treelets, LOD voxels and triangle blocks, and
// the merge that keeps the file independent of how many threads emitted it.
//
// The writer has a main emitter that feeds the model's sink. Parts of a subtree emitted
// in parallel get their own emitters, which defer placing treelets (they record
// placement units instead) and buffer their triangle blocks; the main emitter merges
// them in tree order, packing the units into its own blocks, so nodes pack exactly as
// if one thread had emitted everything.
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

// Sibling treelets a deferred emitter would have placed in a block of `level`.
struct Unit {
    std::size_t level;
    Pending data;
};

class SubtreeEmitter {
public:
    SubtreeEmitter(const ModelWriterParams& params, ProgressCounter& counter, BlockStream out, bool defer);

    // The part whose kd-tree is being emitted (kept by the caller meanwhile).
    void bind(const KdTree* tree, const TriangleSource& source) {
        tree_ = tree;
        src_ = source;
    }

    // Emits the treelet rooted at kd node `root` and everything below it. `jobs`, when
    // given, is asked for each child treelet first: it returns true (and the child's root
    // treelet) when that subtree was emitted elsewhere and is now merged into this one.
    using JobLookup = std::function<bool(std::uint32_t kd_node, Pending& root)>;
    Pending emit_kd_treelet(std::uint32_t root, const Box3f& cell, std::size_t level, const JobLookup* jobs = nullptr);

    // Finishes a LOD node whose children are finished: samples its voxel, places the
    // children side by side one level down (or records them as a unit when deferring),
    // and records where they went.
    void finish_lod(TreeletNode& node, Pending* a, Pending* b, std::size_t level, Pending& self);

    // Lays out a finished treelet of `level` into `out`.
    void serialise(std::vector<TreeletNode>& treelet, std::size_t level, Pending& out) {
        serialise_treelet(treelet, level, stats, out, p_.kd.quantized_splits);
    }

    // Moves a part emitted in parallel into these streams: its triangle blocks follow
    // ours (their ids become base + id), and its placement units are packed into our
    // node blocks in the order the part made them, children before parents, so each
    // LOD node learns its children's block and offset before it is placed itself.
    // `root` is the part's root treelet, whose ids are resolved too.
    void merge(SubtreeEmitter& part, std::vector<StoredBlock>& triangle_blocks, Pending& root);

private:
    const ModelWriterParams& p_;
    ProgressCounter& counter_;
    BlockStream out_;  // declared before the block packers that write into it
    bool defer_;
    std::vector<Unit> units_;
    std::deque<std::vector<TreeletNode>> treelets_;  // by depth of emit_kd_treelet; a deque keeps them in place
    std::size_t depth_ = 0;
    static constexpr std::uint64_t kProgressBatch = 1 << 14;
    std::uint64_t unreported_ = 0;  // leaf references not yet added to counter_
    const KdTree* tree_ = nullptr;
    TriangleSource src_;

public:
    ModelWriterStats stats;
    NodeBlocks nodes;
    TriangleBlocks triangles;
};

}  // namespace vastray::writer
