// Decodes a whole built model (every block, already decompressed and verified) into an
// in-core Scene: the same kd-tree, re-encoded in the in-core node layout, with triangles
// indexed by their input ids. This is the full-detail path for one-shot renders and
// checks; interactive rendering reads blocks through the cache instead.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "vastray/scene.h"

namespace vastray {

struct DecodeInput {
    std::vector<const std::uint8_t*> blocks;  // raw block bytes by global block id
    std::vector<std::size_t> sizes;
    // First block of each stream, level-major with tier_count streams per level (one per
    // level in an untiered file); the last level holds triangles.
    std::vector<std::uint32_t> stream_first;
    std::uint32_t tier_count = 1;
    bool tiered = false;                      // FLAG_TIERED: block references carry a tier
    Vec3d centre;
    Box3f root_cell;
    std::uint64_t triangle_ids = 0;           // one more than the largest input triangle id
    bool has_colours = false;
    bool quantized_splits = false;            // FLAG_QUANTIZED_SPLITS: 4-byte basic nodes
    bool packed_treelets = false;             // FLAG_PACKED_TREELETS: LOD words in 4-byte units
    bool voxel_errors = false;                // FLAG_VOXEL_ERRORS: LOD splits as steps, beside an error code
    bool quantized_vertices = false;          // FLAG_QUANTIZED_VERTICES: vertices on the root cell's grid
    bool compact_triangles = false;           // FLAG_COMPACT_TRIANGLES: compact triangle blocks
};

std::shared_ptr<Scene> decode_model(const DecodeInput& in);

}  // namespace vastray
