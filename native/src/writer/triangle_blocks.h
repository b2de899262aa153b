// Triangle blocks (docs/FORMAT.md §11): leaf triangle lists packed into 64 KB blocks of
// list entries, triangle records and vertices shared within the block (paper 000 §4.6),
// one stream of blocks per coarseness tier (§15).
#pragma once

#include <array>
#include <cstddef>
#include <memory>
#include <cstdint>
#include <cstring>
#include <stdexcept>
#include <utility>
#include <vector>

#include "vastray/format.h"
#include "vastray/model_writer.h"
#include "writer/block_stream.h"
#include "writer/voxel_sampling.h"

namespace vastray::writer {

// Open addressing for the per-block dedup tables (at most a few thousand entries, so
// a fixed table cleared through its used-slot list beats a node-based map).
template <typename Key, typename Hash>
class SmallMap {
public:
    explicit SmallMap(std::size_t capacity_log2)
        : mask_((std::size_t{1} << capacity_log2) - 1), keys_(mask_ + 1), values_(mask_ + 1, kFree) {}
    // Returns the value for key, inserting `fresh` if absent.
    std::uint32_t find_or_insert(const Key& key, std::uint32_t fresh, bool& inserted) {
        std::size_t i = Hash{}(key) & mask_;
        for (;;) {
            if (values_[i] == kFree) {
                // Callers bound what a block can hold well below this; never loop forever.
                if (4 * (used_.size() + 1) > 3 * (mask_ + 1)) throw std::length_error("block dedup table full");
                keys_[i] = key;
                values_[i] = fresh;
                used_.push_back(i);
                inserted = true;
                return fresh;
            }
            if (keys_[i] == key) {
                inserted = false;
                return values_[i];
            }
            i = (i + 1) & mask_;
        }
    }
    void clear() {
        for (std::size_t i : used_) values_[i] = kFree;
        used_.clear();
    }

private:
    static constexpr std::uint32_t kFree = 0xffffffffu;
    std::size_t mask_;
    std::vector<Key> keys_;
    std::vector<std::uint32_t> values_;
    std::vector<std::size_t> used_;
};

struct IdHash {
    std::size_t operator()(std::uint32_t v) const { return static_cast<std::size_t>(v * 0x9E3779B1u) >> 7; }
};
struct VertexKey {
    std::uint32_t bits[3];  // the exact float bits of x, y, z
    bool operator==(const VertexKey& o) const { return bits[0] == o.bits[0] && bits[1] == o.bits[1] && bits[2] == o.bits[2]; }
};
struct VertexHash {
    std::size_t operator()(const VertexKey& k) const {
        std::uint64_t h = k.bits[0] * 0x9E3779B97F4A7C15ull;
        h ^= (h >> 29) + k.bits[1] * 0xBF58476D1CE4E5B9ull;
        h ^= (h >> 31) + k.bits[2] * 0x94D049BB133111EBull;
        return static_cast<std::size_t>(h ^ (h >> 32));
    }
};

// The triangles a part's leaves refer to, indexed by the kd-tree's triangle ids: the
// builder's records (docs/FORMAT.md, "Building a model"), `stride` bytes each: nine f32
// corners (model-local), the u32 input id, and the u32 colour 0x00BBGGRR when the model
// has colours; and one facet per triangle.
struct TriangleSource {
    const std::uint8_t* records = nullptr;
    std::size_t stride = 40;
    bool has_colours = false;
    const Facet* facets = nullptr;

    const Vec3f* corners(std::size_t t) const { return reinterpret_cast<const Vec3f*>(records + stride * t); }
    std::uint32_t id(std::size_t t) const { return word(t, 36); }
    std::uint32_t colour(std::size_t t) const { return word(t, 40); }

private:
    std::uint32_t word(std::size_t t, std::size_t at) const {
        std::uint32_t w;
        std::memcpy(&w, records + stride * t + at, 4);
        return w;
    }
};

// A leaf whose triangles lie in a block that is still open: its first list entry there
// and what add_leaf was given.
struct OpenLeaf {
    std::uint32_t first;
    const std::uint32_t* tris;
    std::uint32_t count;
};

// The triangle blocks of one tier.
class TriangleBlocks {
public:
    // `vertex_steps`: the grid of FLAG_QUANTIZED_VERTICES (null: f32 vertices as given).
    // `compact`: FLAG_COMPACT_TRIANGLES blocks (format.h) instead of the plain layout.
    TriangleBlocks(bool has_colours, const Vec3f* vertex_steps, bool compact, std::uint32_t tier, RawBlockStream& out,
                   ModelWriterStats& stats)
        : has_colours_(has_colours), quantized_(vertex_steps != nullptr), compact_(compact),
          steps_(vertex_steps ? *vertex_steps : Vec3f(1, 1, 1)),
          max_vertices_(compact ? kCompactMaxVertices : quantized_ ? 3 * kMaxTriangles : kMaxVertices),
          max_triangles_(compact ? kCompactMaxTriangles : kMaxTriangles), tier_(tier), out_(out), stats_(stats),
          id_map_(compact ? 15 : 13), vertex_map_(compact ? 16 : quantized_ ? 15 : 13), palette_map_(compact ? 15 : 1) {
        reset_span();
    }

    // Blocks closed so far: the id the next block gets.
    std::uint32_t blocks() const { return blocks_; }
    // A triangle block emitted elsewhere took the next id (parallel merge).
    void skip_block() { ++blocks_; }

    // Ends a part emitted in parallel: the leaves of the open block go to `out` instead
    // of a block of their own, for the merge to add to the block it has open (so a
    // part's last, partly filled block does not stay one). Returns false, after closing
    // the block, when it holds the end of a leaf that began in an earlier block.
    bool take_open_leaves(std::vector<OpenLeaf>& out);

    // Adds one leaf's triangles (soup indices); returns (block id, first): the leaf's
    // first list entry, or in a compact block the byte offset of its leaf record. A
    // leaf's list normally lies in one block. A leaf too big for one (a fan of
    // thousands of triangles around a vertex, which no split can separate) continues
    // at entry 0 (the first leaf record) of the following triangle blocks.
    std::pair<std::uint32_t, std::uint32_t> add_leaf(const std::uint32_t* tris, std::uint32_t count,
                                                     const TriangleSource& src);

    // Closes the current block (if it holds anything) and emits it.
    void flush();

private:
    // Quantized: header word 3, the bit length of the block's span of grid indices on
    // each axis (format.h), so the encoding follows what the block holds.
    std::uint32_t packing() const {
        if (!quantized_ || grid_.empty()) return 0;
        std::uint32_t word = 0;
        for (int a = 0; a < 3; ++a) word |= format::bit_length(static_cast<std::uint32_t>(k_hi_[a] - k_lo_[a])) << (8 * a);
        return word;
    }
    format::TriangleBlockLayout layout() const {
        return format::TriangleBlockLayout::of(list_.size(), ids_.size(), verts_.size(), has_colours_, quantized_,
                                               packing());
    }
    // The raw size of the block as it stands, in its layout.
    std::size_t size() const { return compact_ ? compact_size() : layout().end; }
    void reset_span();
    void clear_open();
    std::array<std::int32_t, 3> grid_index(const Vec3f& p) const;
    void extend_span(const std::array<std::int32_t, 3>& k);
    void truncate(std::size_t list_size, std::size_t tris, std::size_t verts);
    void clear_maps();
    // Inserts triangles into the current block; false when it stopped because the block
    // certainly cannot hold them.
    bool insert(const std::uint32_t* tris, std::uint32_t count, const TriangleSource& src);
    // A leaf tried whole in the current block, then in a fresh one; false when it fits
    // in neither (the block is left empty).
    bool add_whole(const std::uint32_t* tris, std::uint32_t count, const TriangleSource& src, std::uint32_t& first);
    std::vector<std::uint8_t> plain_bytes(const format::TriangleBlockLayout& l) const;

    // ---- compact blocks (FLAG_COMPACT_TRIANGLES) ----
    // A leaf record: its run of list entries and the first triangle it may bring in.
    struct Record {
        std::size_t begin, end;
        std::uint32_t base;
        bool partial;  // the leaf continues in the next block
    };
    // What a record's size depends on, replayed from its entries.
    struct RecordShape {
        std::uint32_t entries = 0, old = 0, max_distance = 0;
        std::size_t bits(bool partial) const;
    };
    // A group's fields: the range of its corners and palette indices, and how its ids
    // are stored (one base, or two for ids from two runs far apart; FORMAT.md §11a).
    struct Range {
        std::uint32_t lo = ~0u, hi = 0;
        void add(std::uint32_t v) {
            lo = std::min(lo, v);
            hi = std::max(hi, v);
        }
        std::uint32_t width() const { return lo > hi ? 0 : format::bit_length(hi - lo); }
    };
    struct IdCoding {
        std::uint32_t base = 0, width = 0;  // the smallest id; bits of an offset
        bool split = false;
        std::uint32_t second = 0, distance_bits = 0;  // split: ids >= second use the second base
        std::size_t bits(std::size_t n) const;        // of the ids in the data record
    };
    struct GroupShape {
        Range corners, palette;
        IdCoding ids;
        std::size_t n = 0;
        std::size_t bits() const;  // of its data record
    };
    static IdCoding id_coding(const std::uint32_t* ids, std::size_t n);
    GroupShape group_shape(std::size_t first, std::size_t n) const;
    void open_record();
    void close_record();
    RecordShape replay(const Record& r) const;
    void add_to_group(std::size_t t);
    std::size_t compact_size() const;
    std::vector<std::uint8_t> compact_bytes() const;
    void reset_compact();

    // A vertex takes 12 bytes, a triangle at least 12 (record, id, list entry); a packed
    // vertex can take less than a byte, but a triangle brings at most three.
    static constexpr std::size_t kMaxVertices = (format::kBlockSize - 16) / 12;
    static constexpr std::size_t kMaxTriangles = (format::kBlockSize - 16) / 12;
    // A compact triangle can take a few bits; these bound the dedup tables (format.h
    // allows 2^16 of each).
    static constexpr std::size_t kCompactMaxTriangles = 1u << 14;
    static constexpr std::size_t kCompactMaxVertices = 1u << 15;

    bool has_colours_;
    bool quantized_;
    bool compact_;
    Vec3f steps_;
    std::size_t max_vertices_, max_triangles_;
    std::uint32_t tier_;
    RawBlockStream& out_;
    ModelWriterStats& stats_;
    std::uint32_t blocks_ = 0;
    std::vector<std::uint16_t> list_, tri_verts_;
    std::vector<std::uint32_t> ids_, colours_;
    std::vector<Vec3f> verts_;
    std::vector<std::array<std::int32_t, 3>> grid_;  // quantized: each vertex's grid index
    std::array<std::int32_t, 3> k_lo_{}, k_hi_{};    // and their bounds in this block
    std::vector<OpenLeaf> open_leaves_;  // the leaves that began in the open block
    bool open_continues_ = false;        // it holds the end of one that began earlier
    // Compact: leaf records, the palette and each triangle's index in it, the groups
    // closed so far (their field bits) and the open one, the block's id range.
    std::vector<Record> records_;
    bool record_open_ = false;  // the last record is still taking entries
    std::size_t closed_record_bytes_ = 0;
    RecordShape open_shape_;
    std::vector<std::uint32_t> palette_, palette_index_;
    std::size_t closed_group_bytes_ = 0;  // the data records of the full groups
    Range block_ids_;
    // Sized for the most entries a block takes (plus one triangle's overshoot) at most 3/4 full.
    SmallMap<std::uint32_t, IdHash> id_map_;
    SmallMap<VertexKey, VertexHash> vertex_map_;
    SmallMap<std::uint32_t, IdHash> palette_map_;  // compact: colour -> palette index
};

// The triangle blocks of every tier, each made on first use (a part uses a few of the
// tiers, and each tier's dedup tables take a few hundred KiB).
class TriangleTiers {
public:
    TriangleTiers(bool has_colours, const Vec3f* vertex_steps, bool compact, RawBlockStream& out, ModelWriterStats& stats)
        : has_colours_(has_colours), compact_(compact), steps_(vertex_steps), out_(out), stats_(stats) {}

    TriangleBlocks& operator[](std::uint32_t tier) {
        if (tiers_.size() <= tier) tiers_.resize(tier + 1);
        if (!tiers_[tier]) {
            tiers_[tier] = std::make_unique<TriangleBlocks>(has_colours_, steps_, compact_, tier, out_, stats_);
        }
        return *tiers_[tier];
    }
    // A tier's blocks, or null when nothing went to it.
    TriangleBlocks* find(std::uint32_t tier) { return tier < tiers_.size() ? tiers_[tier].get() : nullptr; }
    // One more than the highest tier used.
    std::uint32_t size() const { return static_cast<std::uint32_t>(tiers_.size()); }
    // Closes every tier's open block, coarsest first.
    void flush() {
        for (auto& t : tiers_) {
            if (t) t->flush();
        }
    }
    // Drops every tier (a finished parallel part keeps only what its merge needs).
    void release() { tiers_.clear(); }

private:
    bool has_colours_, compact_;
    const Vec3f* steps_;
    RawBlockStream& out_;
    ModelWriterStats& stats_;
    std::vector<std::unique_ptr<TriangleBlocks>> tiers_;
};

}  // namespace vastray::writer
