// A model's blocks while it is being built: one scratch file per level, appended to in
// the order blocks are finished, with the index entry and tier of every block
// (docs/FORMAT.md §5). Within a tier that order is the stream's block order; the
// builder assembles the model file from them once the levels are complete (a file per
// level, not per stream: a model has a few hundred streams, and the file order of a
// level's blocks costs the assembly nothing). The triangle level may instead go
// straight into the model file, past the page cache, where it stays (§3; vastray/
// model_assembly.py): most of a model's bytes then need no copy.
#pragma once

#include <array>
#include <cstdint>
#include <cstdio>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "vastray/model_writer.h"
#include "writer/direct_appender.h"

namespace vastray::writer {

class LevelFiles {
public:
    explicit LevelFiles(std::string dir) : dir_(std::move(dir)) {}
    // The triangle level goes to `output` from byte `start` (a multiple of 4096).
    LevelFiles(std::string dir, const std::string& output, std::uint64_t start);
    ~LevelFiles();
    LevelFiles(const LevelFiles&) = delete;
    LevelFiles& operator=(const LevelFiles&) = delete;

    // Appends a block of stream `tier` to its level's file (level -1: the triangle
    // level). Throws std::runtime_error naming the file when the write fails (a full disk).
    void write(int level, std::uint32_t tier, const StoredBlock& block);
    // Flushes and closes every file.
    void close();
    // The triangle level's bytes in the model file: [start, end); start == end == 0 when
    // it has a scratch file of its own.
    std::uint64_t triangles_start() const { return triangles_start_; }
    std::uint64_t triangles_end() const { return triangles_end_; }
    bool triangles_direct() const { return triangles_direct_; }

    // The file of a level, and its blocks' (stored size, raw size, crc32, codec, tier)
    // in file order.
    std::string path(int level) const;
    const std::map<int, std::vector<std::array<std::uint32_t, 5>>>& entries() const { return entries_; }

private:
    std::string dir_;
    std::map<int, std::FILE*> files_;
    std::map<int, std::vector<std::array<std::uint32_t, 5>>> entries_;
    std::string output_;
    std::unique_ptr<DirectAppender> triangles_;
    std::uint64_t triangles_start_ = 0, triangles_end_ = 0;
    bool triangles_direct_ = false;
};

}  // namespace vastray::writer
