#include "writer/treelet.h"

#include <cstring>
#include <stdexcept>

namespace vastray::writer {

using namespace format;

StreamStats& node_stream(ModelWriterStats& stats, std::size_t level, std::uint32_t tier) {
    if (stats.node_streams.size() <= level) stats.node_streams.resize(level + 1);
    auto& tiers = stats.node_streams[level];
    if (tiers.size() <= tier) tiers.resize(tier + 1);
    return tiers[tier];
}

StreamStats& triangle_stream(ModelWriterStats& stats, std::uint32_t tier) {
    if (stats.triangle_streams.size() <= tier) stats.triangle_streams.resize(tier + 1);
    return stats.triangle_streams[tier];
}

namespace {

void collect(const KdTree& tree, std::uint32_t index, const Box3f& cell, int depth, std::vector<TreeletNode>& nodes) {
    const KdNode& k = tree.nodes[index];
    TreeletNode n;
    n.cell = cell;
    n.kd_node = index;
    if (k.is_leaf()) {
        n.kind = TreeletNode::Leaf;
        nodes.push_back(n);
        return;
    }
    n.axis = k.axis();
    n.split = k.split();
    n.empty = (k.left_empty() ? kLeftEmpty : 0u) | (k.right_empty() ? kRightEmpty : 0u);
    const std::uint32_t left = index + 1, right = index + k.right_offset();
    if (depth == kTreeletHeight - 1) {
        n.kind = TreeletNode::Lod;
        n.kd_left = left;
        n.kd_right = right;
        nodes.push_back(n);
        return;
    }
    const std::size_t self = nodes.size();
    nodes.push_back(n);
    if (!k.left_empty()) {
        nodes[self].left = static_cast<int>(nodes.size());
        collect(tree, left, child_cell(cell, n.axis, n.split, 0), depth + 1, nodes);
    }
    if (!k.right_empty()) {
        nodes[self].right = static_cast<int>(nodes.size());
        collect(tree, right, child_cell(cell, n.axis, n.split, 1), depth + 1, nodes);
    }
}

}  // namespace

void collect_kd_treelet(const KdTree& tree, std::uint32_t root, const Box3f& cell, std::vector<TreeletNode>& nodes) {
    collect(tree, root, cell, 0, nodes);
}

namespace {

// The LOD word of `n` in either layout; a field that does not fit is a logic error.
std::uint32_t lod_word_of(const TreeletNode& n, std::size_t voxel_off, bool packed) {
    const auto voxel4 = static_cast<std::uint32_t>(voxel_off / 4);
    if (packed) {
        const std::uint32_t right4 = n.right_from_left / 4, child4 = n.child_off / 4;
        if (voxel4 > kPackedVoxelOffMax || right4 > kPackedRightMax || child4 > kPackedChildOffMax ||
            (n.right_from_left | n.child_off) % 4 != 0) {
            throw std::logic_error("LOD node field overflow");
        }
        return packed_lod_word(n.axis, n.empty, voxel4, right4, child4);
    }
    const std::uint32_t right8 = n.right_from_left / 8, child8 = n.child_off / 8;
    if (voxel4 > 127 || right8 > 63 || child8 > 8191 || (n.right_from_left | n.child_off) % 8 != 0) {
        throw std::logic_error("LOD node field overflow");
    }
    return lod_word(n.axis, n.empty, voxel4, right8, child8);
}

}  // namespace

void serialise_treelet(std::vector<TreeletNode>& nodes, ModelWriterStats& stats, Pending& out, bool quantized,
                       bool packed, bool voxel_errors) {
    const std::size_t basic_size = quantized ? 4 : 8;
    out.nodes = static_cast<std::uint32_t>(nodes.size());
    out.voxels = 0;
    out.error = nodes.empty() ? std::numeric_limits<float>::infinity() : nodes[0].error;
    std::size_t cursor = 0;
    for (TreeletNode& n : nodes) {
        n.offset = cursor;
        cursor += n.kind == TreeletNode::Lod ? lod_node_size(quantized) : (n.kind == TreeletNode::Basic ? basic_size : 8);
        std::uint64_t& kind_count = n.kind == TreeletNode::Lod    ? stats.lod_nodes
                                    : n.kind == TreeletNode::Leaf ? stats.leaves
                                                                  : stats.basic_nodes;
        ++kind_count;
        stats.empty_children += (n.empty & kLeftEmpty ? 1 : 0) + (n.empty & kRightEmpty ? 1 : 0);
    }
    std::size_t voxel_at[7] = {};
    if (nodes.size() > 7) throw std::logic_error("a treelet has at most seven nodes");
    for (std::size_t i = 0; i < nodes.size(); ++i) {
        if (nodes[i].kind != TreeletNode::Lod) continue;
        voxel_at[i] = cursor;
        cursor += 4 * static_cast<std::size_t>(nodes[i].voxel_words);
    }
    const std::size_t align = packed ? 4 : 8;
    cursor = (cursor + align - 1) & ~(align - 1);
    out.bytes.assign(cursor, 0);
    auto put = [&](std::size_t at, std::uint32_t w) { std::memcpy(out.bytes.data() + at, &w, 4); };
    for (std::size_t i = 0; i < nodes.size(); ++i) {
        const TreeletNode& n = nodes[i];
        switch (n.kind) {
            case TreeletNode::Basic: {
                const std::size_t right_gap = n.right >= 0 ? nodes[static_cast<std::size_t>(n.right)].offset - n.offset : 0;
                if (quantized) {
                    std::uint32_t q = 0;
                    if (!split_step(n.cell.lo[n.axis], n.cell.hi[n.axis], n.split, q)) {
                        throw std::logic_error("a split plane is not on its cell's quantization grid");
                    }
                    // No left child: the right one follows at +4 (the field then reads 1).
                    const auto right4 = static_cast<std::uint32_t>(right_gap / 4);
                    put(n.offset, quantized_basic_word(n.axis, n.empty, right4, q));
                    break;
                }
                const auto right8 = static_cast<std::uint32_t>(right_gap / 8);
                put(n.offset, basic_word(n.axis, n.empty, right8));
                put(n.offset + 4, float_bits(n.split));
                break;
            }
            case TreeletNode::Lod: {
                out.voxels++;
                put(n.offset, lod_word_of(n, voxel_at[i] - n.offset, packed));
                if (voxel_errors) {
                    std::uint32_t q = 0;
                    if (!split_step(n.cell.lo[n.axis], n.cell.hi[n.axis], n.split, q)) {
                        throw std::logic_error("a split plane is not on its cell's quantization grid");
                    }
                    put(n.offset + 4, lod_split_word(q, n.error_code));
                } else {
                    put(n.offset + 4, float_bits(n.split));
                }
                if (!quantized) put(n.offset + 8, float_bits(n.radius));  // quantized: derived from the cell
                put(n.offset + lod_child_block_at(quantized), n.child_block);
                if (n.unit >= 0) out.patches.push_back({static_cast<std::uint32_t>(n.offset), n.unit});
                for (int s = 0; s < n.voxel_words; ++s) put(voxel_at[i] + 4 * static_cast<std::size_t>(s), n.voxel[s]);
                break;
            }
            case TreeletNode::Leaf:
                put(n.offset, leaf_word(n.first, n.count));
                put(n.offset + 4, n.tri_block);
                out.patches.push_back({static_cast<std::uint32_t>(n.offset + 4), -1});
                break;
        }
    }
}

}  // namespace vastray::writer
