// A built model opened for block reads: its header fields and block index, checked on
// open (docs/FORMAT.md §4, §5, §13), and a verified read of any block. This is the
// native reader behind the block cache; vastray/modelfile.py is the Python reader used
// by the builder and `vastray inspect`.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "vastray/vecmath.h"

namespace vastray {

struct BlockEntry {
    std::uint64_t offset = 0;
    std::uint32_t stored_size = 0, raw_size = 0, crc32 = 0, codec = 0;
};

class ModelIndex {
public:
    // Throws std::runtime_error naming the path and what is wrong.
    explicit ModelIndex(const std::string& path);
    ~ModelIndex();
    ModelIndex(const ModelIndex&) = delete;
    ModelIndex& operator=(const ModelIndex&) = delete;

    const std::string& path() const { return path_; }
    bool has_colours() const { return has_colours_; }
    bool quantized_splits() const { return quantized_splits_; }  // FLAG_QUANTIZED_SPLITS
    bool packed_treelets() const { return packed_treelets_; }    // FLAG_PACKED_TREELETS (version 7)
    bool voxel_errors() const { return voxel_errors_; }          // FLAG_VOXEL_ERRORS (version 8)
    bool quantized_vertices() const { return quantized_vertices_; }  // FLAG_QUANTIZED_VERTICES
    bool compact_triangles() const { return compact_triangles_; }  // FLAG_COMPACT_TRIANGLES
    const Vec3f& vertex_steps() const { return vertex_steps_; }  // that flag's grid (format.h)
    const Vec3d& centre() const { return centre_; }
    const Box3f& root_cell() const { return root_cell_; }
    std::uint64_t triangle_count() const { return triangle_count_; }
    std::uint64_t input_triangles() const { return input_triangles_; }
    std::uint64_t file_size() const { return file_size_; }
    std::uint32_t part_count() const { return part_count_; }  // 0 without a parts section
    std::size_t block_count() const { return entries_.size(); }
    std::size_t level_count() const { return level_first_.size() - 1; }
    // First global block id of each level; one extra entry holds block_count.
    const std::vector<std::uint32_t>& level_first() const { return level_first_; }
    // FLAG_TIERED: each level is tier_count() streams (1 in an untiered file), and
    // stream_first() the first block of stream L * tier_count() + k, level-major, with one
    // extra entry holding block_count (format.h).
    bool tiered() const { return tiered_; }
    std::uint32_t tier_count() const { return tier_count_; }
    const std::vector<std::uint32_t>& stream_first() const { return stream_first_; }
    const BlockEntry& entry(std::size_t block) const { return entries_[block]; }
    std::size_t level_of(std::size_t block) const;
    std::string level_name(std::size_t block) const;  // "LOD level 3" or "triangle level"

    // Reads, checks and decodes block `block` into `out` (at least raw_size bytes), using
    // `scratch` for the stored bytes. Safe to call from several threads at once (pread).
    // Returns an empty string on success, else what went wrong; never throws.
    std::string read_block(std::size_t block, std::uint8_t* out, std::vector<std::uint8_t>& scratch) const;
    // Asks the kernel to start reading blocks [first, last] (consecutive ids; one call per
    // run of them that is also consecutive in the file) into the page cache; returns at
    // once. Only a hint: failures are ignored.
    void read_ahead(std::size_t first, std::size_t last) const;

private:
    std::string path_;
    int fd_ = -1;
    bool has_colours_ = false;
    bool quantized_splits_ = false, packed_treelets_ = false, voxel_errors_ = false, quantized_vertices_ = false, compact_triangles_ = false;
    Vec3f vertex_steps_{1, 1, 1};
    Vec3d centre_;
    Box3f root_cell_;
    std::uint64_t triangle_count_ = 0, input_triangles_ = 0, file_size_ = 0;
    std::uint32_t part_count_ = 0;
    std::vector<std::uint32_t> level_first_, stream_first_;
    bool tiered_ = false;
    std::uint32_t tier_count_ = 1;
    std::vector<BlockEntry> entries_;
};

}  // namespace vastray
