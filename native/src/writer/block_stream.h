// Where a writer's finished raw blocks go: straight to the model's sink, or into a
// buffer that a parallel part's merge hands on later.
#pragma once

#include <cstdint>
#include <functional>
#include <vector>

#include "vastray/model_writer.h"

namespace vastray::writer {

// level >= 0: a node level; -1: the triangle level; `tier` the stream of that level.
// Blocks arrive compressed (store_block), on the thread that finished them.
using BlockStream = std::function<void(int level, std::uint32_t tier, StoredBlock&& block)>;

// What the block packers hand on: a finished raw block, compressed by whoever receives
// it (SubtreeEmitter, with the model's compressor), on the packer's thread.
using RawBlockStream = std::function<void(int level, std::uint32_t tier, const std::vector<std::uint8_t>& raw)>;

}  // namespace vastray::writer
