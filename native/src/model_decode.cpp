#include "vastray/model_decode.h"

#include <stdexcept>
#include <string>
#include <utility>

#include "vastray/format.h"

namespace vastray {

using namespace format;

namespace {

class Decoder {
public:
    explicit Decoder(const DecodeInput& in) : in_(in), steps_(vertex_grid_steps(in.root_cell.lo, in.root_cell.hi)) {
        if (in.tier_count == 0 || in.stream_first.size() % in.tier_count != 0 ||
            in.stream_first.size() / in.tier_count < 2) {
            throw std::runtime_error("model has no levels");
        }
        tri_level_ = in.stream_first.size() / in.tier_count - 1;
        vertices_.resize(3 * in.triangle_ids);
        seen_.assign(in.triangle_ids, 0);
        if (in.has_colours) colours_.resize(3 * in.triangle_ids);
    }

    std::shared_ptr<Scene> run() {
        walk(in_.stream_first[0], 0, 0, 0, in_.root_cell);
        KdTree tree;
        tree.nodes = std::move(nodes_);
        tree.tri_ids = std::move(tri_ids_);
        tree.bounds = in_.root_cell;
        tree.stats.nodes = tree.nodes.size();
        tree.stats.references = tree.tri_ids.size();
        return std::make_shared<Scene>(in_.centre, std::move(vertices_), std::move(colours_), std::move(tree));
    }

private:
    [[noreturn]] static void bad(std::size_t block, const std::string& what) {
        throw std::runtime_error("model block " + std::to_string(block) + ": " + what);
    }

    std::uint32_t word(std::size_t block, std::size_t off) const {
        if (off + 4 > in_.sizes[block]) bad(block, "node at offset " + std::to_string(off) + " runs past the block end");
        std::uint32_t w;
        std::memcpy(&w, in_.blocks[block] + off, 4);
        return w;
    }

    // The global block a node's block reference names in `level`, and the end of its
    // stream (a leaf too big for one block continues up to there).
    std::pair<std::size_t, std::size_t> block_of(std::size_t level, std::uint32_t reference, std::size_t from) const {
        const std::uint32_t tier = ref_tier(reference, in_.tiered), relative = ref_relative(reference, in_.tiered);
        const std::string where = in_.tiered ? " of tier " + std::to_string(tier) : std::string();
        if (tier >= in_.tier_count) {
            bad(from, "child block " + std::to_string(relative) + where + " is outside level " + std::to_string(level));
        }
        const std::size_t s = stream_index(level, tier, in_.tier_count);
        const std::size_t end = s + 1 < in_.stream_first.size() ? in_.stream_first[s + 1] : in_.blocks.size();
        const std::size_t b = std::size_t{in_.stream_first[s]} + relative;
        if (b >= end) bad(from, "child block " + std::to_string(relative) + where + " is outside level " + std::to_string(level));
        return {b, end};
    }

    void walk(std::size_t block, std::size_t off, std::size_t level, int depth, const Box3f& cell) {
        if (depth > 200) bad(block, "tree deeper than 200 levels (cycle?)");
        const std::uint32_t w = word(block, off);
        if (!is_inner(w)) {
            leaf(block, w, word(block, off + 4));
            return;
        }
        if (axis_of(w) > 2) bad(block, "split axis 3 at offset " + std::to_string(off));
        // A quantized model's basic nodes are 4 bytes, their split a step of the cell; so
        // is a LOD node's split with voxel errors (word 1, beside the error code).
        const bool quantized = in_.quantized_splits && !is_lod(w);
        const std::size_t size = quantized ? 4 : 8;
        float split;
        if (quantized) {
            split = dequantize_split(cell.lo[axis_of(w)], cell.hi[axis_of(w)], basic_split_step(w));
        } else if (is_lod(w) && in_.voxel_errors) {
            const std::uint32_t word1 = word(block, off + 4);
            if (lod_split_word_overflows(word1) || lod_split_step(word1) == 0) {
                bad(block, "LOD split word out of range at offset " + std::to_string(off));
            }
            split = dequantize_split(cell.lo[axis_of(w)], cell.hi[axis_of(w)], lod_split_step(word1));
        } else {
            split = bits_float(word(block, off + 4));
        }
        const std::uint32_t empty = w & (kLeftEmpty | kRightEmpty);
        const bool has_l = (empty & kLeftEmpty) == 0, has_r = (empty & kRightEmpty) == 0;
        if (!has_l && !has_r) bad(block, "inner node with two empty children");
        const std::size_t self = nodes_.size();
        nodes_.push_back(KdNode::inner(axis_of(w), split, 0, (has_l ? 0 : KdNode::kLeftEmpty) | (has_r ? 0 : KdNode::kRightEmpty)));
        std::size_t l_block = block, r_block = block, l_off = off + size, r_off = 0, child_level = level;
        if (is_lod(w)) {
            if (level + 1 >= tri_level_) bad(block, "LOD node in the last node level");
            child_level = level + 1;
            l_block = r_block = block_of(child_level, word(block, off + lod_child_block_at(in_.quantized_splits)), block).first;
            const LodOffsets o = lod_offsets(w, in_.packed_treelets);
            l_off = o.first_child;
            r_off = has_l ? l_off + o.right_from_left : l_off;
        } else {
            r_off = has_l ? off + size * static_cast<std::size_t>(basic_right_off8(w)) : off + size;
            if (has_r && r_off <= off + size && has_l) bad(block, "right child offset does not point past the left child");
        }
        Box3f lcell = cell, rcell = cell;
        lcell.hi[axis_of(w)] = split;
        rcell.lo[axis_of(w)] = split;
        if (has_l) walk(l_block, l_off, child_level, depth + 1, lcell);
        if (has_r) {
            const std::size_t right_index = nodes_.size();
            walk(r_block, r_off, child_level, depth + 1, rcell);
            if (has_l) nodes_[self] = KdNode::inner(axis_of(w), split, static_cast<std::uint32_t>(right_index - self), 0);
            else nodes_[self] = KdNode::inner(axis_of(w), split, 1, KdNode::kLeftEmpty);
        }
    }

    struct TriangleBlockView {
        std::size_t block = 0;
        const std::uint8_t* data = nullptr;
        std::uint32_t lists = 0, tris = 0, verts = 0;
        TriangleBlockLayout layout;
    };

    TriangleBlockView triangle_block(std::size_t b) const {
        TriangleBlockView v;
        v.block = b;
        v.data = in_.blocks[b];
        if (in_.sizes[b] < 16) bad(b, "triangle block shorter than its header");
        std::uint32_t header[4];
        std::memcpy(header, v.data, sizeof header);
        v.lists = header[0];
        v.tris = header[1];
        v.verts = header[2];
        v.layout = TriangleBlockLayout::read(v.data, in_.has_colours, in_.quantized_vertices);
        if (v.layout.end == ~std::size_t{0}) bad(b, "unknown vertex encoding " + std::to_string(header[3]));
        if (v.layout.end != in_.sizes[b]) bad(b, "triangle block size does not match its section counts");
        return v;
    }

    // A leaf's entries run from `first` to the end of its block's list and, for leaves
    // too big for one block, on from entry 0 of the following triangle blocks.
    void leaf(std::size_t from, std::uint32_t w, std::uint32_t tri_block) {
        if (leaf_count(w) == 0) {  // no triangles: its block reference is not read
            nodes_.push_back(KdNode::leaf(static_cast<std::uint32_t>(tri_ids_.size()), 0));
            return;
        }
        if (in_.compact_triangles) {
            compact_leaf(from, w, tri_block);
            return;
        }
        const auto [first_block, stream_end] = block_of(tri_level_, tri_block, from);
        TriangleBlockView tb = triangle_block(first_block);
        std::uint32_t entry = leaf_first(w);
        const std::uint32_t count = leaf_count(w);
        nodes_.push_back(KdNode::leaf(static_cast<std::uint32_t>(tri_ids_.size()), count));
        for (std::uint32_t i = 0; i < count; ++i, ++entry) {
            while (entry >= tb.lists) {
                if (tb.block + 1 >= stream_end) bad(tb.block, "leaf list runs past the last triangle block");
                tb = triangle_block(tb.block + 1);
                entry = 0;
            }
            const std::size_t b = tb.block;
            const std::uint8_t* data = tb.data;
            const TriangleBlockLayout& l = tb.layout;
            std::uint16_t local;
            std::memcpy(&local, data + l.list + 2 * std::size_t{entry}, 2);
            if (local >= tb.tris) bad(b, "list entry points past the triangle section");
            std::uint32_t id;
            std::memcpy(&id, data + l.ids + 4 * std::size_t{local}, 4);
            if (id >= seen_.size()) bad(b, "triangle id " + std::to_string(id) + " is out of range");
            tri_ids_.push_back(id);
            if (seen_[id]) continue;
            seen_[id] = 1;
            for (int k = 0; k < 3; ++k) {
                std::uint16_t v;
                std::memcpy(&v, data + l.triangles + 6 * std::size_t{local} + 2 * static_cast<std::size_t>(k), 2);
                if (v >= tb.verts) bad(b, "triangle points past the vertex section");
                vertices_[3 * std::size_t{id} + static_cast<std::size_t>(k)] = l.vertex(data, v, steps_);
            }
            if (in_.has_colours) {
                std::uint32_t c;
                std::memcpy(&c, data + l.colours + 4 * std::size_t{local}, 4);
                for (int k = 0; k < 3; ++k) colours_[3 * std::size_t{id} + static_cast<std::size_t>(k)] = static_cast<std::uint8_t>(c >> (8 * k));
            }
        }
    }

    CompactTriangleBlock compact_block(std::size_t b) const {
        CompactTriangleBlock v{};
        if (in_.sizes[b] < compact::kHeader) bad(b, "triangle block shorter than its header");
        if (!CompactTriangleBlock::parse(in_.blocks[b], in_.sizes[b], in_.has_colours, in_.quantized_vertices, v)) {
            bad(b, "compact triangle block header is damaged (counts, widths or section offsets)");
        }
        if (v.end != in_.sizes[b]) bad(b, "triangle block size does not match its section counts");
        return v;
    }

    // A compact block (format.h): the leaf's record at byte `first` and, for a leaf that
    // continues, the first record of each following triangle block.
    void compact_leaf(std::size_t from, std::uint32_t w, std::uint32_t tri_block) {
        auto [b, stream_end] = block_of(tri_level_, tri_block, from);
        CompactTriangleBlock tb = compact_block(b);
        std::uint32_t at = leaf_first(w), remaining = leaf_count(w);
        nodes_.push_back(KdNode::leaf(static_cast<std::uint32_t>(tri_ids_.size()), remaining));
        while (remaining > 0) {
            CompactLeafRecord record{};
            if (!record.open(tb, at, remaining)) bad(b, "leaf record lies outside the records or has a bad count");
            for (std::uint32_t i = 0; i < record.count(); ++i) {
                std::uint32_t local;
                if (!record.next(local)) {
                    bad(b, record.overrun() ? "leaf record runs past the records section"
                                            : "list entry points past the triangle section");
                }
                CompactTriangleBlock::Group g{};
                if (!tb.group(local / compact::kGroup, g) || !tb.fits(g)) bad(b, "triangle group is damaged (widths or extent)");
                const std::uint32_t k = local - g.first;
                const std::uint32_t id = tb.id(g, k);
                if (id >= seen_.size()) bad(b, "triangle id " + std::to_string(id) + " is out of range");
                tri_ids_.push_back(id);
                if (seen_[id]) continue;
                seen_[id] = 1;
                std::uint32_t v[3];
                tb.corners(g, k, v);
                for (int c = 0; c < 3; ++c) {
                    if (v[c] >= tb.verts) bad(b, "triangle points past the vertex section");
                    vertices_[3 * std::size_t{id} + static_cast<std::size_t>(c)] = tb.vertex(v[c], steps_);
                }
                if (in_.has_colours) {
                    const std::uint32_t p = tb.palette_index(g, k);
                    if (p >= tb.palette_size) bad(b, "triangle colour points past the palette");
                    const std::uint32_t rgb = tb.colour(p);
                    for (int c = 0; c < 3; ++c) colours_[3 * std::size_t{id} + static_cast<std::size_t>(c)] = static_cast<std::uint8_t>(rgb >> (8 * c));
                }
            }
            remaining -= record.count();
            if (remaining > 0) {
                if (b + 1 >= stream_end) bad(b, "leaf list runs past the last triangle block");
                tb = compact_block(++b);
                at = compact::kHeader;
            }
        }
    }

    const DecodeInput& in_;
    Vec3f steps_;  // the quantized vertex grid (used only with FLAG_QUANTIZED_VERTICES)
    std::size_t tri_level_ = 0;
    HugeVector<KdNode> nodes_;
    HugeVector<std::uint32_t> tri_ids_;
    HugeVector<Vec3f> vertices_;
    std::vector<std::uint8_t> seen_, colours_;
};

}  // namespace

std::shared_ptr<Scene> decode_model(const DecodeInput& in) { return Decoder(in).run(); }

}  // namespace vastray
