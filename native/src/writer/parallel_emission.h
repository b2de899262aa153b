// Emitting one in-core part on all lanes. The part's tree is cut into jobs: subtrees
// below chosen treelet roots, each emitted by its own deferring emitter on the thread
// pool. The main emitter walks the treelets above the jobs meanwhile and, reaching a
// job, waits for it and merges it (its placement units and triangle blocks, in tree
// order), so the file is what one thread emitting job after job would write.
//
// The jobs are chosen from the tree alone (never from the number of threads): the file
// does not depend on how many threads emit it.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "vastray/kdtree.h"
#include "vastray/model_writer.h"
#include "writer/subtree_emitter.h"

namespace vastray::writer {

struct EmissionJob {
    std::uint32_t node;  // the kd node that roots the job's treelet
    Box3f cell;
    std::size_t level;  // the LOD level of that treelet
    std::uint32_t tier;  // its coarseness tier (its parent LOD node's)
    std::uint64_t references;
};

// Treelet roots below the part's root treelet, in tree order: the biggest is split into
// its child treelets until none holds more than 1/32 of the part's leaf references (and
// 2^18 at least), or it has no child treelets. Empty when the part is too small to be
// worth it.
// The jobs' tiers are `main`'s (bound to the part).
std::vector<EmissionJob> choose_jobs(const KdTree& tree, const Box3f& cell, std::size_t level, const SubtreeEmitter& main);

// Emits the whole part through `main` (bound to the part), returns its root treelet;
// `tier` is the root treelet's (that of the LOD node above the part).
Pending emit_part(SubtreeEmitter& main, const KdTree& tree, const TriangleSource& src, const Box3f& cell,
                  std::size_t level, std::uint32_t tier, const ModelWriterParams& params, ProgressCounter& counter,
                  unsigned lanes);

}  // namespace vastray::writer
