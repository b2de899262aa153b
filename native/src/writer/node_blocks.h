// Node blocks (docs/FORMAT.md §7): finished treelets packed, sibling pair by sibling
// pair, into 64 KB blocks of their LOD level's stream (its coarseness tier). Block ids
// count the closed blocks of a stream from 0, so a parent can store its children's id
// before the stream is complete.
#pragma once

#include <cstddef>
#include <cstdint>
#include <utility>
#include <vector>

#include "vastray/model_writer.h"
#include "writer/block_stream.h"
#include "writer/treelet.h"

namespace vastray::writer {

class NodeBlocks {
public:
    NodeBlocks(RawBlockStream& out, ModelWriterStats& stats) : out_(out), stats_(stats) {}

    // Places sibling treelets (either may be null) contiguously in one block of stream
    // (`level`, `tier`), closing its current block first if they do not fit; returns the
    // block id in the stream and the first one's offset in it.
    std::pair<std::uint32_t, std::size_t> place(std::size_t level, std::uint32_t tier, const Pending* a,
                                                const Pending* b);

    // Closes the current block of a stream, if it holds anything.
    void flush(std::size_t level, std::uint32_t tier);
    // Closes every stream's current block, level by level, coarsest tier first.
    void flush_all();
    // Whether a block of `level` has been started (closed or not), in any tier.
    bool started(std::size_t level) const;

private:
    std::vector<std::uint8_t>& open(std::size_t level, std::uint32_t tier);

    RawBlockStream& out_;
    ModelWriterStats& stats_;
    std::vector<std::vector<std::vector<std::uint8_t>>> open_;  // the current block of each stream
};

}  // namespace vastray::writer
