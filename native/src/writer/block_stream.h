// Where a writer's finished raw blocks go: straight to the model's sink, or into a
// buffer that a parallel part's merge hands on later.
#pragma once

#include <cstdint>
#include <functional>
#include <vector>

namespace vastray::writer {

// level >= 0: a node level; -1: the triangle level.
using BlockStream = std::function<void(int level, std::vector<std::uint8_t>&& bytes)>;

}  // namespace vastray::writer
