// A model's blocks while it is being built: one scratch file per level, appended to in
// the order blocks are finished, with the index entry and tier of every block
// (docs/FORMAT.md §5). Within a tier that order is the stream's block order; the
// builder assembles the model file from them once the levels are complete, each level's
// streams one after the other (a file per level, not per stream: a model has a few
// hundred streams, and the file order of a level's blocks costs the assembly nothing).
#pragma once

#include <array>
#include <cstdint>
#include <cstdio>
#include <map>
#include <string>
#include <vector>

#include "vastray/model_writer.h"

namespace vastray::writer {

class LevelFiles {
public:
    explicit LevelFiles(std::string dir) : dir_(std::move(dir)) {}
    ~LevelFiles();
    LevelFiles(const LevelFiles&) = delete;
    LevelFiles& operator=(const LevelFiles&) = delete;

    // Appends a block of stream `tier` to its level's file (level -1: the triangle
    // level). Throws std::runtime_error naming the file when the write fails (a full disk).
    void write(int level, std::uint32_t tier, const StoredBlock& block);
    // Flushes and closes every file.
    void close();

    // The file of a level, and its blocks' (stored size, raw size, crc32, codec, tier)
    // in file order.
    std::string path(int level) const;
    const std::map<int, std::vector<std::array<std::uint32_t, 5>>>& entries() const { return entries_; }

private:
    std::string dir_;
    std::map<int, std::FILE*> files_;
    std::map<int, std::vector<std::array<std::uint32_t, 5>>> entries_;
};

}  // namespace vastray::writer
