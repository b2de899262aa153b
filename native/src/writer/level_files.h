// A model's blocks while it is being built: the index entry, tier and file offset of
// every block (docs/FORMAT.md §5), by level, in the order the blocks are finished (within
// a tier, the stream's order). The blocks go either straight into the model file, past
// the page cache, behind room kept for the header and the index (vastray/
// model_assembly.py writes those and moves the last blocks into what the index leaves of
// that room: nothing is copied but them), or into a scratch file per level that the
// builder assembles the model file from (a file per level, not per stream: a model has a
// few hundred streams, and the file order of a level's blocks costs the assembly nothing).
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
    // A scratch file per level in `dir`.
    explicit LevelFiles(std::string dir) : dir_(std::move(dir)) {}
    // Every block into the model file `output`, from byte `start` (a multiple of 4096).
    LevelFiles(const std::string& output, std::uint64_t start);
    ~LevelFiles();
    LevelFiles(const LevelFiles&) = delete;
    LevelFiles& operator=(const LevelFiles&) = delete;

    // Appends a block of stream `tier` of `level` (-1: the triangle level). Throws
    // std::runtime_error naming the file when the write fails (a full disk).
    void write(int level, std::uint32_t tier, const StoredBlock& block);
    // Writes out and closes every file.
    void close();

    // The file holding a level's blocks, and per level its blocks' (stored size, raw
    // size, crc32, codec, tier) and offsets in that file, in the order written.
    std::string path(int level) const;
    const std::map<int, std::vector<std::array<std::uint32_t, 5>>>& entries() const { return entries_; }
    const std::map<int, std::vector<std::uint64_t>>& offsets() const { return offsets_; }
    // Into the model file: where the first block starts and the last ends, and whether
    // the writes went past the page cache. Both 0 with scratch files.
    std::uint64_t start() const { return start_; }
    std::uint64_t end() const { return end_; }
    bool direct() const { return direct_; }

private:
    std::string dir_;
    std::map<int, std::FILE*> files_;
    std::map<int, std::uint64_t> sizes_;
    std::map<int, std::vector<std::array<std::uint32_t, 5>>> entries_;
    std::map<int, std::vector<std::uint64_t>> offsets_;
    std::string output_;
    std::unique_ptr<DirectAppender> model_;
    std::uint64_t start_ = 0, end_ = 0;
    bool direct_ = false;
};

}  // namespace vastray::writer
