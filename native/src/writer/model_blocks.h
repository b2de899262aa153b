// Where a build's blocks go: appended to the model file as they are finished, past the
// page cache, behind room kept for the header and the index (vastray/model_assembly.py
// writes those at the end and moves the last blocks into what the index leaves of that
// room; docs/FORMAT.md §3). Kept per level: each block's index entry, tier and offset
// (§5), in the order written, which within a tier is the stream's order.
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "vastray/model_writer.h"
#include "writer/direct_appender.h"

namespace vastray::writer {

class ModelBlocks {
public:
    // Every block into the model file `output`, from byte `start` (a multiple of 4096).
    ModelBlocks(const std::string& output, std::uint64_t start);

    // Appends a block of stream `tier` of `level` (-1: the triangle level). Throws
    // std::runtime_error naming the file when the write fails (a full disk).
    void write(int level, std::uint32_t tier, const StoredBlock& block);
    // Writes out what is buffered and closes the file.
    void close();

    const std::string& path() const { return output_; }
    // Per level, its blocks' (stored size, raw size, crc32, codec, tier) and offsets in
    // the file, in the order written.
    const std::map<int, std::vector<std::array<std::uint32_t, 5>>>& entries() const { return entries_; }
    const std::map<int, std::vector<std::uint64_t>>& offsets() const { return offsets_; }
    // Where the first block starts and the last ends; whether the writes went past the
    // page cache.
    std::uint64_t start() const { return start_; }
    std::uint64_t end() const { return end_; }
    bool direct() const { return direct_; }

private:
    std::string output_;
    std::unique_ptr<DirectAppender> file_;
    std::map<int, std::vector<std::array<std::uint32_t, 5>>> entries_;
    std::map<int, std::vector<std::uint64_t>> offsets_;
    std::uint64_t start_ = 0, end_ = 0;
    bool direct_ = false;
};

}  // namespace vastray::writer
