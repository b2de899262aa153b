// Node blocks (docs/FORMAT.md §7): finished treelets packed, sibling pair by sibling
// pair, into 64 KB blocks of their LOD level. Block ids count the closed blocks of a
// level from 0, so a parent can store its children's id before the level is complete.
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
    NodeBlocks(BlockStream& out, ModelWriterStats& stats) : out_(out), stats_(stats) {}

    // Places sibling treelets (either may be null) contiguously in one block of `level`,
    // closing the current block first if they do not fit; returns the block id and the
    // first one's offset in it.
    std::pair<std::uint32_t, std::size_t> place(std::size_t level, const Pending* a, const Pending* b);

    // Closes the current block of `level`, if it holds anything.
    void flush(std::size_t level);
    // Closes every level's current block.
    void flush_all();
    // Whether a block of `level` has been started (closed or not).
    bool started(std::size_t level) const;

private:
    void ensure(std::size_t level);

    BlockStream& out_;
    ModelWriterStats& stats_;
    std::vector<std::vector<std::uint8_t>> open_;  // the current block of each level
};

}  // namespace vastray::writer
