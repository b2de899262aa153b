// Ray traversal of a built model straight from its cached blocks, with level of detail
// (paper 000 Algorithm 1). The walk is the in-core kd traversal (traverse.h), step for
// step, over the on-disk node layout (format.h), plus two ways to stop early at a LOD
// node's voxel:
//   - the LOD test: the voxel's enclosing-sphere radius R is small enough for the ray's
//     footprint, R <= (cone_t0 + t_entry) * cone (PoE metric for primary and shadow rays,
//     solid-angle metric for AO rays: both are cones from a ray origin);
//   - missing data: a child treelet or triangle block that is not in the cache is
//     requested, and the ray hits the last voxel it passed instead. It never waits.
// With cone = 0 and every block present the answers equal the in-core traversal's.
#pragma once

#include <cstdint>
#include <cstring>
#include <type_traits>
#include <utility>
#include <vector>

#include "vastray/block_cache.h"
#include "vastray/format.h"
#include "vastray/isa.h"
#include "vastray/prefetch.h"
#include "vastray/traverse.h"

VASTRAY_KERNEL_BEGIN

constexpr std::uint32_t kVoxelPrim = 0xfffffffeu;  // LodHit::prim of a voxel hit

struct LodRay {
    Ray ray;
    float cone_t0 = 0;  // distance already covered by the cone before this ray's origin
    float cone = 0;     // LOD cone slope; 0 disables the LOD test (full detail)
};

struct LodHit : Hit {
    // Triangle hits: the triangle block and the triangle's index in it.
    const std::uint8_t* tri_block = nullptr;
    std::uint32_t local = 0;
    // Voxel hits: the sample for the face the ray entered, and the voxel's radius.
    std::uint32_t sample = 0;
    float voxel_radius = 0;
    int face = 0;
};

// One lane's view of a model during one frame: block lookups that stamp the working
// set, request what is missing and count what happened. Lanes sit side by side in a
// vector, one per thread: each starts on a cache line of its own, so one thread's
// counters never share a line with the next lane's fields (false sharing).
struct alignas(64) LodLane {
    BlockCache* cache = nullptr;
    CachedModel* model = nullptr;
    std::uint32_t tick = 0;
    const std::uint32_t* level_first = nullptr;
    std::uint32_t tri_level = 0;
    // The streams of each level (FLAG_TIERED; one per level untiered): first block of
    // stream L * tier_count + k, and past the last one block_count (ModelIndex).
    const std::uint32_t* stream_first = nullptr;
    std::uint32_t tier_count = 1;
    bool tiered = false;
    bool has_colours = false;
    bool quantized_splits = false;  // FLAG_QUANTIZED_SPLITS: 4-byte basic nodes, splits on their cell's grid
    bool packed_treelets = false;   // FLAG_PACKED_TREELETS: LOD words in 4-byte units (format.h)
    bool voxel_errors = false;      // FLAG_VOXEL_ERRORS: LOD splits as steps, and a surface error (format.h)
    bool quantized_vertices = false;  // FLAG_QUANTIZED_VERTICES: bit-packed grid offsets in triangle blocks
    Vec3f vertex_steps{1, 1, 1};      // that grid's steps
    bool compact_triangles = false;   // FLAG_COMPACT_TRIANGLES: compact triangle blocks (format.h)
    std::vector<std::pair<CachedModel*, std::uint32_t>> requests;  // first requests
    std::uint64_t lookups = 0, hits = 0, missing = 0, bad = 0, ws_blocks = 0, ws_bytes = 0;
    std::uint64_t node_visits = 0, triangle_tests = 0, voxel_hits = 0;

    // `priority` is the fetch priority of a missing block: a float, or a callable that
    // gives it, called only when the block is missing (a packet's priority takes a
    // reduction over its lanes, wasted on the blocks that are there).
    template <typename Priority>
    const std::uint8_t* lookup(std::uint32_t block, const Priority& priority) {
        ++lookups;
        // Blocks are published and evicted only between frames, and a lane lives for one
        // frame, so a block found once stays where it is: neighbouring rays cross into the
        // same treelets and leaves, and find them here without the cache's tables.
        Seen& seen = seen_[block % kSeen];
        if (seen.block == block) {
            ++hits;
            return seen.data;
        }
        const std::int32_t slot = model->slot(block);
        if (slot >= 0) {
            ++hits;
            if (cache->touch(slot, tick)) {
                ++ws_blocks;
                ws_bytes += cache->slot_raw_size(slot);
            }
            seen = {block, cache->slot_data(slot)};
            return seen.data;
        }
        ++missing;
        if (slot == CachedModel::kBad) {
            ++bad;
        } else if (model->request(block, priority_value(priority))) {
            requests.emplace_back(model, block);
        }
        return nullptr;
    }

private:
    template <typename Priority>
    static float priority_value(const Priority& priority) {
        if constexpr (std::is_invocable_v<const Priority&>) {
            return priority();
        } else {
            return priority;
        }
    }
    static constexpr std::uint32_t kSeen = 64;
    struct Seen {
        std::uint32_t block = ~0u;  // no block id is that large (the index holds fewer)
        const std::uint8_t* data = nullptr;
    };
    Seen seen_[kSeen];
};

namespace lod_detail {

template <typename T>
inline T load(const std::uint8_t* p) {
    T v;
    std::memcpy(&v, p, sizeof v);
    return v;
}

// A voxel: its samples, enclosing radius (how far a ray leaving it must start) and the
// error its LOD test compares (the radius, or with FLAG_VOXEL_ERRORS the surface error).
// Voxel and NodeRef are plain aggregates on purpose: traversal stacks hold 64 of them,
// and default member initialisers would zero the whole stack for every ray.
struct Voxel {
    const std::uint8_t* samples;
    float radius;
    float error;
};

inline void hit_voxel(const Voxel& v, int entry_axis, const Ray& ray, float t, LodHit& hit) {
    hit.t = t;
    hit.prim = kVoxelPrim;
    hit.tri_block = nullptr;
    hit.voxel_radius = v.radius;
    const int face = 2 * entry_axis + (ray.dir[entry_axis] >= 0.0f ? 0 : 1);
    hit.face = face;
    hit.sample = format::voxel_face_sample(v.samples, face);
}

// A node in a cached block: the block's bytes, the node's offset, its LOD level, and its
// cell (a quantized model's basic nodes store their split as a step of it).
struct NodeRef {
    const std::uint8_t* block;
    std::uint32_t off, level;
    float lo[3], hi[3];
};

inline NodeRef root_ref(const std::uint8_t* block, const Box3f& cell) {
    return {block, 0, 0, {cell.lo.x, cell.lo.y, cell.lo.z}, {cell.hi.x, cell.hi.y, cell.hi.z}};
}

// An inner node's split position: word 1, or the step of its cell on the split axis (a
// quantized model's basic node in word 0; with FLAG_VOXEL_ERRORS a LOD node in word 1).
inline float split_of(bool quantized, bool voxel_errors, const NodeRef& node, std::uint32_t w) {
    if (quantized) {
        const int a = std::min(format::axis_of(w), 2);
        if (!format::is_lod(w)) return format::dequantize_split(node.lo[a], node.hi[a], format::basic_split_step(w));
        if (voxel_errors) {
            const auto word1 = load<std::uint32_t>(node.block + node.off + 4);
            return format::dequantize_split(node.lo[a], node.hi[a], format::lod_split_step(word1));
        }
    }
    return format::bits_float(load<std::uint32_t>(node.block + node.off + 4));
}

// What the LOD test of the LOD node at `node` compares: its radius, or with
// FLAG_VOXEL_ERRORS the error its word 1 codes.
inline float lod_test_error(bool voxel_errors, const std::uint8_t* node, float radius) {
    return voxel_errors ? format::lod_error(radius, format::lod_error_code(load<std::uint32_t>(node + 4))) : radius;
}

// A LOD node's voxel: its samples, its radius (a quantized model derives it from the
// cell instead of storing it) and its error (lod_test_error).
inline Voxel voxel_of(bool quantized, bool packed, bool voxel_errors, const NodeRef& node, std::uint32_t w) {
    const float radius =
        quantized ? format::cell_radius(Vec3f(node.hi[0] - node.lo[0], node.hi[1] - node.lo[1], node.hi[2] - node.lo[2]))
                  : format::bits_float(load<std::uint32_t>(node.block + node.off + 8));
    return {node.block + node.off + format::lod_offsets(w, packed).voxel, radius,
            lod_test_error(voxel_errors, node.block + node.off, radius)};
}

// The stream a block reference of `level` names: its first block, and one past its last
// (the end is the start for a reference to no stream, so every id is outside it).
inline std::pair<std::uint64_t, std::uint64_t> referenced_stream(const LodLane& lane, std::uint32_t level,
                                                                 std::uint32_t reference) {
    const std::uint32_t tier = format::ref_tier(reference, lane.tiered);
    if (tier >= lane.tier_count) return {0, 0};
    const std::uint32_t* s = lane.stream_first + format::stream_index(level, tier, lane.tier_count);
    return {std::uint64_t{s[0]} + format::ref_relative(reference, lane.tiered), s[1]};
}

// The block holding a LOD node's child treelets, or null when it is not cached (then it
// is requested) or the node is damaged (points outside the next level).
template <typename Priority>
inline const std::uint8_t* lod_child_block(LodLane& lane, const NodeRef& node, const Priority& priority) {
    if (node.level + 1 >= lane.tri_level) return nullptr;  // no node level below: damaged
    const auto [block, end] = referenced_stream(
        lane, node.level + 1, load<std::uint32_t>(node.block + node.off + format::lod_child_block_at(lane.quantized_splits)));
    return block < end ? lane.lookup(static_cast<std::uint32_t>(block), priority) : nullptr;
}

// The offsets of an inner node's children in their block (the node's own for a basic
// node, the child block for a LOD node); false for a damaged node, whose offsets would
// loop or leave the block. The right child never lies before the left (a basic node's
// offset is at least two nodes, a LOD node's at least 0), so when present it is the one
// furthest on. Basic nodes are 8 bytes, 4 in a quantized model; offsets count in that.
// `packed`: FLAG_PACKED_TREELETS, the LOD word's offsets in 4-byte units.
template <bool Quantized>
inline bool child_offsets(std::uint32_t w, std::uint32_t off, bool packed, std::uint32_t& l_off, std::uint32_t& r_off) {
    using namespace format;
    const bool has_l = (w & kLeftEmpty) == 0, has_r = (w & kRightEmpty) == 0;
    if (is_lod(w)) {
        const LodOffsets o = lod_offsets(w, Quantized && packed);
        l_off = o.first_child;
        r_off = has_l ? l_off + o.right_from_left : l_off;
    } else {
        constexpr std::uint32_t kNodeSize = Quantized ? 4 : 8;
        const std::uint32_t r = basic_right_off8(w);
        if (has_l && has_r && r < 2) return false;
        l_off = off + kNodeSize;
        r_off = has_l ? off + kNodeSize * r : l_off;
    }
    return (has_r ? r_off : l_off) <= kBlockSize - 8;
}

// Root clip that also says through which face the ray enters (the axis of the largest
// near distance), for the shading of a voxel hit on the root's children.
inline bool clip_with_axis(const Ray& ray, const Box3f& box, float& t0, float& t1, int& axis) {
    if (!clip_ray_to_box(ray, box, t0, t1)) return false;
    axis = 0;
    float best = -std::numeric_limits<float>::infinity();
    for (int a = 0; a < 3; ++a) {
        if (ray.dir[a] == 0.0f) continue;
        const float tn = ((ray.dir[a] > 0 ? box.lo[a] : box.hi[a]) - ray.org[a]) / ray.dir[a];
        if (tn > best) {
            best = tn;
            axis = a;
        }
    }
    return true;
}

// Vertex i of a plain triangle block, for the kernels: out of line, but compiled for the
// kernel's own ISA (flatten inlines the layout's reader into it). A plain call reaches the
// one out-of-line copy of TriangleBlockLayout::vertex in the module, the SSE2 core's, and
// on an Intel Xeon its legacy SSE code met dirty upper halves of the vector registers
// where the packets of 4 call it: their frames ran about 4x slower. Inlining it into the
// walks instead cost 5 % at 10^7 (docs/native-core.md, "No calls out of the hot loops").
// LeafTriangles reads float vertices itself and calls this for quantized ones only.
[[gnu::noinline, gnu::flatten]] inline Vec3f plain_vertex(const format::TriangleBlockLayout& layout,
                                                         const std::uint8_t* tb, std::size_t i, const Vec3f& steps) {
    return layout.vertex(tb, i, steps);
}

// Walks the triangles of one leaf: its run of list entries in a triangle block and, for
// leaves too big for one block, on into the following blocks. Entries that point
// outside their block are skipped; a block that is missing (requested) or has a
// damaged header ends the walk with `missing()` true. A compact block (format.h) is
// read the same way through its leaf record; a record that is damaged ends the walk
// like a missing block, since the entries after a bad one cannot be found.
// `Priority` as in LodLane::lookup.
template <typename Priority = float>
class LeafTriangles {
public:
    LeafTriangles(LodLane& lane, const std::uint8_t* leaf_node, Priority priority)
        : lane_(lane), priority_(priority) {
        const std::uint32_t w = load<std::uint32_t>(leaf_node);
        left_ = format::leaf_count(w);
        empty_ = left_ == 0;
        entry_ = format::leaf_first(w);
        // A leaf of no triangles reads no block (the kd builder leaves a few, where an
        // empty-space cut keeps nothing); its reference is not read.
        if (left_ == 0) return;
        const auto [block, end] = referenced_stream(lane, lane.tri_level, load<std::uint32_t>(leaf_node + 4));
        block_id_ = block;
        end_ = end;
        open(block_id_);
    }

    bool missing() const { return block_ == nullptr && !empty_; }

    // The next triangle (its index in the current block); false at the end of the leaf
    // or when a block is missing.
    bool next(Vec3f& v0, Vec3f& v1, Vec3f& v2, std::uint32_t& local) {
        if (lane_.compact_triangles) return next_compact(v0, v1, v2, local);
        while (block_ && left_ > 0) {
            --left_;
            while (block_ && entry_ >= entries_) {  // a big leaf continues in the next block
                entry_ = 0;
                open(++block_id_);
            }
            if (!block_) return false;
            const std::uint32_t e = entry_++;
            local = load<std::uint16_t>(block_ + layout_.list + 2 * std::size_t{e});
            if (local >= tris_) continue;
            const std::uint8_t* corner = block_ + layout_.triangles + 6 * std::size_t{local};
            const std::uint32_t i0 = load<std::uint16_t>(corner), i1 = load<std::uint16_t>(corner + 2),
                                i2 = load<std::uint16_t>(corner + 4);
            if (i0 >= verts_ || i1 >= verts_ || i2 >= verts_) continue;
            if (!layout_.packed) {
                // Float vertices are three loads, read here: three calls of the out-of-line
                // reader per triangle cost an AMD EPYC 1-4 % of a full-detail frame.
                v0 = layout_.float_vertex(block_, i0);
                v1 = layout_.float_vertex(block_, i1);
                v2 = layout_.float_vertex(block_, i2);
                return true;
            }
            v0 = plain_vertex(layout_, block_, i0, lane_.vertex_steps);
            v1 = plain_vertex(layout_, block_, i1, lane_.vertex_steps);
            v2 = plain_vertex(layout_, block_, i2, lane_.vertex_steps);
            return true;
        }
        return false;
    }
    const std::uint8_t* block() const { return block_; }
    // Starts loading the input id and colour of triangle `local` of a plain block, which
    // a closest hit needs once the walk is over (resolve_triangle_ids, the shading).
    void prefetch_hit(std::uint32_t local) const {
        if (lane_.compact_triangles) return;
        prefetch_line(block_ + layout_.ids + 4 * std::size_t{local});
        if (lane_.has_colours) prefetch_line(block_ + layout_.colours + 4 * std::size_t{local});
    }
    // The input id of triangle `local` of the current block, read only when needed: the
    // ids live in their own section, a cache line away from the vertices.
    std::uint32_t id(std::uint32_t local) const {
        if (lane_.compact_triangles) {
            return group_for(local) ? compact_.id(group_, local - group_.first) : kNoHit;
        }
        return load<std::uint32_t>(block_ + layout_.ids + 4 * std::size_t{local});
    }

private:
    // A big leaf's list continues in the next blocks of its stream, never past it.
    void open(std::uint64_t id) {
        block_ = id < end_ ? lane_.lookup(static_cast<std::uint32_t>(id), priority_) : nullptr;
        if (!block_) return;
        if (lane_.compact_triangles) {
            // A damaged header or record: treat as missing. An empty leaf has no record.
            group_index_ = ~0u;
            record_left_ = 0;
            if (left_ == 0) return;
            if (!format::CompactTriangleBlock::parse(block_, format::kBlockSize, lane_.has_colours,
                                                     lane_.quantized_vertices, compact_) ||
                !record_.open(compact_, entry_, left_)) {
                block_ = nullptr;
                return;
            }
            record_left_ = record_.count();
            return;
        }
        entries_ = load<std::uint32_t>(block_);
        tris_ = load<std::uint32_t>(block_ + 4);
        verts_ = load<std::uint32_t>(block_ + 8);
        layout_ = format::TriangleBlockLayout::read(block_, lane_.has_colours, lane_.quantized_vertices);
        if (layout_.end > format::kBlockSize) block_ = nullptr;  // damaged header: treat as missing
    }

    bool next_compact(Vec3f& v0, Vec3f& v1, Vec3f& v2, std::uint32_t& local) {
        while (block_ && left_ > 0) {
            if (record_left_ == 0) {  // a big leaf continues at the next block's first record
                entry_ = format::compact::kHeader;
                open(++block_id_);
                if (!block_) return false;
            }
            --left_;
            --record_left_;
            if (!record_.next(local)) {
                block_ = nullptr;
                return false;
            }
            std::uint32_t v[3];
            if (!compact_.corners(local, v)) continue;
            if ((v[0] >= compact_.verts) | (v[1] >= compact_.verts) | (v[2] >= compact_.verts)) continue;
            v0 = compact_.vertex(v[0], lane_.vertex_steps);
            v1 = compact_.vertex(v[1], lane_.vertex_steps);
            v2 = compact_.vertex(v[2], lane_.vertex_steps);
            return true;
        }
        return false;
    }
    // Decodes the group holding triangle `local` unless it is the one decoded last (a
    // leaf's triangles mostly come in runs); false for a damaged group.
    bool group_for(std::uint32_t local) const {
        const std::uint32_t g = local / format::compact::kGroup;
        if (g == group_index_) return true;
        group_index_ = ~0u;
        if (!compact_.group(g, group_)) return false;
        group_index_ = g;
        return true;
    }

    LodLane& lane_;
    Priority priority_;
    const std::uint8_t* block_ = nullptr;
    std::uint64_t block_id_ = 0, end_ = 0;
    std::uint32_t left_ = 0, entry_ = 0, entries_ = 0, tris_ = 0, verts_ = 0;
    bool empty_ = false;  // a leaf of no triangles: nothing to read, nothing missing
    format::TriangleBlockLayout layout_;
    // Compact blocks: the block's view, the leaf record being read, the last group
    // (uninitialised until open() parses a compact block).
    format::CompactTriangleBlock compact_;
    format::CompactLeafRecord record_;
    std::uint32_t record_left_ = 0;
    mutable format::CompactTriangleBlock::Group group_;
    mutable std::uint32_t group_index_ = ~0u;
};

}  // namespace lod_detail

namespace lod_detail {

// The input id of triangle `local` of the triangle block at tb (LeafTriangles::id
// without a leaf open), kNoHit for a damaged compact block. The walks record a closest
// hit as its block and index and read the id once, when the walk is over: the ids lie
// a cache line away from the vertices, and reading them at every closer hit cost a
// miss per leaf that held one.
inline std::uint32_t triangle_id(const LodLane& lane, const std::uint8_t* tb, std::uint32_t local) {
    if (lane.compact_triangles) {
        format::CompactTriangleBlock b;
        format::CompactTriangleBlock::Group g;
        if (!format::CompactTriangleBlock::parse(tb, format::kBlockSize, lane.has_colours, lane.quantized_vertices, b) ||
            !b.group(local / format::compact::kGroup, g)) {
            return kNoHit;
        }
        return b.id(g, local - g.first);
    }
    const auto layout = format::TriangleBlockLayout::read(tb, lane.has_colours, lane.quantized_vertices);
    return load<std::uint32_t>(tb + layout.ids + 4 * std::size_t{local});
}

// Hits whose prim is still a triangle's index in its block (the packet walks' closest
// hits) get the triangle's input id.
inline void resolve_triangle_ids(const LodLane& lane, LodHit* hits, int n) {
    for (int i = 0; i < n; ++i) {
        LodHit& h = hits[i];
        if (h.tri_block && h.prim != kNoHit && h.prim != kVoxelPrim) h.prim = triangle_id(lane, h.tri_block, h.local);
    }
}

// A leaf's triangles asked for from memory, one wait at a time, by a walk that stops
// for memory and runs other walks meanwhile (PacketWalker). Each wait asks for
// what the previous one's lines tell where to find: in a plain block the list entries,
// the triangle records, the vertices; in a compact one the leaf record, the group
// headers, the groups' corner fields, the vertices (one wait more, as a compact
// triangle's corners are found through its group's header).
struct LeafPrefetch {
    const std::uint8_t* block = nullptr;
    int stage = 0;  // 0: no leaf; 1 .. last - 1: waiting for the stage's lines; last: all asked
    int last = 0;

    // Whether the walk should wait once more (and call next() when it is back).
    bool waiting() const { return stage > 0 && stage < last; }

    // Asks for the triangle block header and the list entries (a compact block: the
    // leaf record) of the leaf at `node`; false when the block is not cached (the
    // leaf's walk requests it and moves on).
    bool start(const LodLane& lane, const std::uint8_t* node) {
        if (format::leaf_count(load<std::uint32_t>(node)) == 0) return false;  // reads no block
        const auto [id, end] = referenced_stream(lane, lane.tri_level, load<std::uint32_t>(node + 4));
        if (id >= end) return false;
        const std::int32_t slot = lane.model->slot(static_cast<std::uint32_t>(id));
        if (slot < 0) return false;
        block = lane.cache->slot_data(slot);
        const std::size_t first = format::leaf_first(load<std::uint32_t>(node));
        prefetch_line(block);
        if (lane.compact_triangles) {
            prefetch_line(block + first);
            last = 4;
        } else {
            prefetch_line(block + 16 + 2 * first);
            last = 3;
        }
        stage = 1;
        return true;
    }

    // The next wait of a leaf: with the lines of the last one at hand, asks for the next.
    void next(const LodLane& lane, const std::uint8_t* node) {
        if (lane.compact_triangles) {
            next_compact(lane, node);
            return;
        }
        const std::uint8_t* tb = block;
        const auto layout = format::TriangleBlockLayout::read(tb, lane.has_colours, lane.quantized_vertices);
        ++stage;
        if (layout.end > format::kBlockSize) return;  // a damaged header: LeafTriangles says so
        if (stage == 2) {
            // The list entries are here: the range of the leaf's first triangles, kept for
            // the next wait.
            const std::uint32_t w = load<std::uint32_t>(node);
            const std::uint32_t entries = load<std::uint32_t>(tb), tris = load<std::uint32_t>(tb + 4);
            const std::uint32_t first = format::leaf_first(w), end = std::min(first + format::leaf_count(w), entries);
            std::uint32_t t_lo = ~0u, t_hi = 0;
            for (std::uint32_t e = first; e < end && e < first + 32; ++e) {
                const std::uint32_t t = load<std::uint16_t>(tb + layout.list + 2 * std::size_t{e});
                if (t >= tris) continue;
                t_lo = std::min(t_lo, t);
                t_hi = std::max(t_hi, t);
            }
            t_lo_ = t_lo;
            t_hi_ = t_hi;
            if (t_lo > t_hi) return;
            prefetch_range(tb + layout.triangles + 6 * std::size_t{t_lo}, 6 * std::size_t{t_hi - t_lo + 1});
            return;
        }
        const std::uint32_t t_lo = t_lo_, t_hi = t_hi_;
        if (t_lo > t_hi) return;
        const std::uint32_t verts = load<std::uint32_t>(tb + 8);
        std::uint32_t v_lo = ~0u, v_hi = 0;
        for (std::uint32_t t : {t_lo, t_hi}) {
            for (int k = 0; k < 3; ++k) {
                const std::uint32_t v = load<std::uint16_t>(tb + layout.triangles + 6 * std::size_t{t} + 2 * k);
                if (v >= verts) continue;
                v_lo = std::min(v_lo, v);
                v_hi = std::max(v_hi, v);
            }
        }
        if (v_lo > v_hi) return;
        const std::size_t base = layout.vertices + (layout.packed ? 12 : 0);
        prefetch_range(tb + base + layout.record * v_lo, layout.record * (v_hi - v_lo + 1));
    }

private:
    // A compact block's waits. The triangles a leaf brings in are numbered together, and
    // its older ones are mostly a few places back, so the first and last of its first
    // entries bound the group headers, corner fields and vertices it reads. Whatever is
    // damaged asks for nothing more: LeafTriangles finds it and says so.
    void next_compact(const LodLane& lane, const std::uint8_t* node) {
        const int wait = stage++;
        format::CompactTriangleBlock b;
        if (!format::CompactTriangleBlock::parse(block, format::kBlockSize, lane.has_colours,
                                                 lane.quantized_vertices, b)) {
            stage = last;
            return;
        }
        if (wait == 1) {
            // The record is here: the range of the leaf's triangles, and their group headers.
            const std::uint32_t w = load<std::uint32_t>(node);
            format::CompactLeafRecord record;
            if (!record.open(b, format::leaf_first(w), format::leaf_count(w))) {
                stage = last;
                return;
            }
            std::uint32_t lo = ~0u, hi = 0;
            const std::uint32_t n = std::min<std::uint32_t>(record.count(), 32);
            for (std::uint32_t e = 0; e < n; ++e) {
                std::uint32_t t;
                if (!record.next(t)) break;
                lo = std::min(lo, t);
                hi = std::max(hi, t);
            }
            if (lo > hi) {
                stage = last;
                return;
            }
            t_lo_ = lo;
            t_hi_ = hi;
            const std::size_t from = std::size_t{lo / format::compact::kGroup} * b.header_bits / 8;
            const std::size_t to = (std::size_t{hi / format::compact::kGroup} + 1) * b.header_bits / 8 + 8;
            prefetch_range(block + b.groups + from, to - from);
            return;
        }
        if (wait == 2) {
            // The group headers are here: the corner fields of the first and last triangle.
            std::size_t lo = ~std::size_t{0}, hi = 0;
            for (std::uint32_t t : {t_lo_, t_hi_}) {
                format::CompactTriangleBlock::Group g;
                if (!b.group(t / format::compact::kGroup, g)) continue;
                const std::size_t at = static_cast<std::size_t>(g.at - block) +
                                       std::size_t{3} * g.cw * (t - g.first) / 8;
                lo = std::min(lo, at);
                hi = std::max(hi, at + 8);
            }
            if (lo > hi) {
                stage = last;
                return;
            }
            prefetch_range(block + lo, hi - lo);
            return;
        }
        // The corner fields are here: the vertices of the first and last triangle.
        std::uint32_t v_lo = ~0u, v_hi = 0;
        for (std::uint32_t t : {t_lo_, t_hi_}) {
            std::uint32_t v[3];
            if (!b.corners(t, v)) continue;
            for (std::uint32_t i : v) {
                if (i >= b.verts) continue;
                v_lo = std::min(v_lo, i);
                v_hi = std::max(v_hi, i);
            }
        }
        if (v_lo > v_hi) return;
        if (b.packed) {
            const std::size_t bit = std::size_t{v_lo} * b.record_bits;
            const std::size_t bytes = (std::size_t{v_hi - v_lo + 1} * b.record_bits + 7) / 8 + 8;
            prefetch_range(block + b.vertices + 12 + bit / 8, bytes);
        } else {
            prefetch_range(block + b.vertices + 12 * std::size_t{v_lo}, 12 * std::size_t{v_hi - v_lo + 1});
        }
    }

    // The lines of [p, p + bytes).
    [[gnu::always_inline]] static void prefetch_range(const std::uint8_t* p, std::size_t bytes) {
        bytes = std::min<std::size_t>(bytes, 6 * 64);
        for (std::size_t b = 0; b < bytes + 63; b += 64) prefetch_line(p + b);
    }

    std::uint32_t t_lo_ = 0, t_hi_ = 0;  // the leaf's first and last triangle (of its first entries)
};

// The walk of one ray below a node (lod_walk), for a model whose basic nodes carry their
// split in word 1 (Quantized = false) or as a step of their cell (true). Only a
// quantized model's walk carries cells: its splits and LOD radii derive from them. The
// position is kept as loose scalars rather than NodeRefs, which the compiler would copy
// whole (and read back as vectors right after writing single fields) at every step.
//
// A single ray walks to its end in one go. It used to stop where it would wait for
// memory (a child treelet, a leaf's triangle data), so that 8 walks in flight could
// overlap their misses as the packets' do; for single rays the stops cost more than
// they hid (docs/out-of-core-rendering.md, "How a ray walks").
template <bool AnyHit, bool Quantized>
class Walker {
public:
    Walker(const LodRay& lray, const ShearedRay& sheared, LodHit& hit, std::uint32_t skip)
        : lray_(&lray), sheared_(sheared), hit_(&hit), skip_(skip) {
        const Ray& ray = lray.ray;
        for (int a = 0; a < 3; ++a) {
            org_[a] = ray.org[a];
            inv_[a] = 1.0f / ray.dir[a];
            dir_negative_[a] = std::signbit(ray.dir[a]);
        }
    }

    // Walks the subtree at `at` to the end, entered with the segment [tmin, tmax] by the
    // face on `entry_axis`, below `voxel`. True when the ray is finished (its hit can no
    // longer change), false when the subtree is done and cells beyond it may still hold a
    // nearer hit.
    // (Every exit goes through the label at the end rather than through lambdas that
    // capture the position by reference: a captured local lives in memory, and the
    // compiler then loads and stores tmin, tmax and the rest at every step.)
    bool run(LodLane& lane, const NodeRef& at, float tmin, float tmax, int entry_axis, Voxel voxel) {
        using namespace format;
        const Ray& ray = lray_->ray;
        const float cone = lray_->cone, cone_t0 = lray_->cone_t0;
        LodHit& hit = *hit_;
        const std::uint8_t* block = at.block;
        std::uint32_t off = at.off, level = at.level;
        int top = 0;
        float lo[3], hi[3];
        if constexpr (Quantized) {
            for (int a = 0; a < 3; ++a) {
                lo[a] = at.lo[a];
                hi[a] = at.hi[a];
            }
        }
        std::uint64_t node_visits = 0;
        bool finished = true;
        Voxel stand_in{nullptr, 0.0f, 0.0f};  // the voxel a finished ray hits, at tmin
        bool leaf = false;
        for (;;) {
            while (!leaf) {
                const std::uint32_t w = load<std::uint32_t>(block + off);
                if (!is_inner(w)) {
                    leaf = true;
                    break;
                }
                ++node_visits;
                const int axis = std::min(axis_of(w), 2);
                const bool lod = is_lod(w);
                const bool has_l = (w & kLeftEmpty) == 0, has_r = (w & kRightEmpty) == 0;
                float split;
                if (Quantized && !lod) {
                    split = dequantize_split(lo[axis], hi[axis], basic_split_step(w));
                } else if (Quantized && lane.voxel_errors) {
                    split = dequantize_split(lo[axis], hi[axis], lod_split_step(load<std::uint32_t>(block + off + 4)));
                } else {
                    split = bits_float(load<std::uint32_t>(block + off + 4));
                }
                const std::uint8_t* child_block = block;
                std::uint32_t child_level = level, l_off, r_off;
                if (lod) {
                    float radius;
                    if constexpr (Quantized) {
                        radius = cell_radius(Vec3f(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]));
                    } else {
                        radius = bits_float(load<std::uint32_t>(block + off + 8));
                    }
                    const float error = lod_test_error(Quantized && lane.voxel_errors, block + off, radius);
                    const Voxel here{block + off + lod_offsets(w, Quantized && lane.packed_treelets).voxel, radius, error};
                    const float reach = cone_t0 + tmin;
                    if (error <= reach * cone) {
                        stand_in = here;
                        goto done;
                    }
                    child_block =
                        lod_child_block(lane, NodeRef{block, off, level, {}, {}}, error / std::max(reach, 1e-30f));
                    if (!child_block) {
                        stand_in = here;
                        goto done;
                    }
                    voxel = here;
                    child_level = level + 1;
                }
                if (!child_offsets<Quantized>(w, off, lane.packed_treelets, l_off, r_off)) goto done;  // damaged

                const float o = org_[axis];
                const float t_split = (split - o) * inv_[axis];
                const float abs_split = std::abs(t_split);
                const float slack = abs_split < std::numeric_limits<float>::infinity() ? abs_split * kSplitSlack : 0.0f;
                const float ts_lo = t_split - slack, ts_hi = t_split + slack;
                const bool below_first = o < split || (o == split && dir_negative_[axis]);
                const bool has_first = below_first ? has_l : has_r, has_second = below_first ? has_r : has_l;
                const std::uint32_t first_off = below_first ? l_off : r_off, second_off = below_first ? r_off : l_off;
                bool to_first, push = false;
                float push_tmin = tmin, push_tmax = tmax;
                int push_axis = entry_axis;
                if (t_split != t_split) {
                    push = true;
                    to_first = true;
                } else if (ts_lo > tmax || t_split <= 0.0f) {
                    to_first = true;
                } else if (ts_hi < tmin) {
                    to_first = false;
                } else if (!has_first) {
                    to_first = false;
                    if (ts_lo > tmin) {
                        tmin = ts_lo;
                        entry_axis = axis;
                    }
                } else {
                    push = true;
                    push_tmin = std::max(tmin, ts_lo);
                    push_axis = ts_lo > tmin ? axis : entry_axis;
                    to_first = true;
                    tmax = std::min(tmax, ts_hi);
                }
                if (push && has_second && top < kStack) {
                    // The second child, with its segment (and, quantized, its cell).
                    if constexpr (Quantized) {
                        float* c = cells_[top];
                        for (int a = 0; a < 3; ++a) {
                            c[a] = lo[a];
                            c[3 + a] = hi[a];
                        }
                        if (below_first) c[axis] = split;  // the second child lies above the plane
                        else c[3 + axis] = split;
                    }
                    stack_[top++] = {child_block, second_off, child_level, push_tmin, push_tmax, push_axis, voxel};
                }
                if (!(to_first ? has_first : has_second)) break;
                if constexpr (Quantized) {
                    // The child below the plane keeps lo, the one above keeps hi.
                    if (to_first == below_first) hi[axis] = split;
                    else lo[axis] = split;
                }
                block = child_block;
                off = to_first ? first_off : second_off;
                level = child_level;
            }
            if (leaf) {
                leaf = false;
                const float priority = voxel.samples ? voxel.error / std::max(cone_t0 + tmin, 1e-30f) : 0.0f;
                LeafTriangles triangles(lane, block + off, priority);
                Vec3f v0, v1, v2;
                std::uint32_t local;
                while (triangles.next(v0, v1, v2, local)) {
                    if (skip_ != kNoHit && triangles.id(local) == skip_) continue;
                    ++lane.triangle_tests;
                    if (intersect_triangle(ray, sheared_, v0, v1, v2, hit)) {
                        hit.tri_block = triangles.block();
                        hit.local = local;
                        if (AnyHit) {
                            hit.prim = triangles.id(local);
                            goto done;
                        }
                        // The input id is read once, at the end (resolve_triangle_ids says why).
                        hit.prim = local;
                        provisional_ = true;
                        triangles.prefetch_hit(local);
                    }
                }
                if (triangles.missing()) {
                    // Triangles not here yet: the last voxel passed stands in for them.
                    if (voxel.samples) {
                        stand_in = voxel;
                        goto done;
                    }
                } else if (hit.prim != kNoHit && hit.t * (1.0f + kSplitSlack) < tmax) {
                    goto done;
                }
            }
            for (;;) {
                if (top == 0) {
                    finished = false;
                    goto done;
                }
                const Entry& e = stack_[--top];
                if (e.tmin > hit.t) continue;
                block = e.block;
                off = e.off;
                level = e.level;
                tmin = e.tmin;
                tmax = e.tmax;
                entry_axis = e.entry_axis;
                voxel = e.voxel;
                if constexpr (Quantized) {
                    for (int a = 0; a < 3; ++a) {
                        lo[a] = cells_[top][a];
                        hi[a] = cells_[top][3 + a];
                    }
                }
                break;
            }
        }
    done:
        if (stand_in.samples) {
            if (tmin < hit.t) hit_voxel(stand_in, entry_axis, ray, tmin, hit);
            ++lane.voxel_hits;
        }
        if (provisional_ && hit.prim != kVoxelPrim) hit.prim = triangle_id(lane, hit.tri_block, hit.local);
        lane.node_visits += node_visits;
        return finished;
    }

private:
    static constexpr int kStack = 64;
    struct Entry {
        const std::uint8_t* block;
        std::uint32_t off, level;
        float tmin, tmax;
        int entry_axis;
        Voxel voxel;
    };

    const LodRay* lray_ = nullptr;
    ShearedRay sheared_;
    LodHit* hit_ = nullptr;
    std::uint32_t skip_ = kNoHit;
    bool provisional_ = false;  // the hit's prim is its triangle's index in tri_block
    float org_[3], inv_[3];
    bool dir_negative_[3];
    Entry stack_[kStack];
    float cells_[Quantized ? kStack : 1][6];  // the entries' cells (quantized models only)
};

template <bool AnyHit, bool Quantized>
inline bool walk(LodLane& lane, const LodRay& lray, const ShearedRay& sheared, const NodeRef& start, float tmin,
                 float tmax, int entry_axis, Voxel voxel, LodHit& hit, std::uint32_t skip) {
    return Walker<AnyHit, Quantized>(lray, sheared, hit, skip).run(lane, start, tmin, tmax, entry_axis, voxel);
}

}  // namespace lod_detail

// The walk of one ray through the subtree at `node`, entered with the segment
// [tmin, tmax] by the face on `entry_axis`, below the voxel last passed (`voxel`).
// Closest hit (AnyHit = false) or any hit (AnyHit = true); voxels count as hits.
// Returns true when the ray is finished (its hit can no longer change: a voxel stood in,
// a hit lies inside its cell, an any-hit ray hit, or a node is damaged), false when the
// subtree is done and cells beyond it may still hold a nearer hit. lod_traverse() walks
// from the root.
template <bool AnyHit>
inline bool lod_walk(LodLane& lane, const LodRay& lray, const ShearedRay& sheared, const lod_detail::NodeRef& node,
                     float tmin, float tmax, int entry_axis, lod_detail::Voxel voxel, LodHit& hit,
                     std::uint32_t skip) {
    return lane.quantized_splits
               ? lod_detail::walk<AnyHit, true>(lane, lray, sheared, node, tmin, tmax, entry_axis, voxel, hit, skip)
               : lod_detail::walk<AnyHit, false>(lane, lray, sheared, node, tmin, tmax, entry_axis, voxel, hit, skip);
}

// Closest hit (AnyHit = false) or any hit (AnyHit = true) of one ray; voxels count as
// hits. `skip` is a triangle never reported (the surface a secondary ray leaves).
template <bool AnyHit>
inline bool lod_traverse(LodLane& lane, const Box3f& root_cell, const LodRay& lray, LodHit& hit,
                         std::uint32_t skip = kNoHit) {
    const Ray& ray = lray.ray;
    float tmin, tmax;
    int entry_axis;
    hit.t = ray.tmax;
    hit.prim = kNoHit;
    if (!lod_detail::clip_with_axis(ray, root_cell, tmin, tmax, entry_axis)) return false;
    const std::uint8_t* block = lane.lookup(lane.level_first[0], 0.0f);
    if (!block) return false;
    lod_walk<AnyHit>(lane, lray, ShearedRay(ray.dir), lod_detail::root_ref(block, root_cell), tmin, tmax, entry_axis,
                     {nullptr, 0.0f, 0.0f}, hit, skip);
    return hit.prim != kNoHit;
}

// Closest hits of n independent rays: hits[i] is what lod_traverse<false> gives rays[i].
// One ray after another. Eight walks in flight per thread, each stopping for a child
// treelet and a leaf's triangle data as the packets do, measured 1.07x this on 2
// December and 0.61-0.86x on 5 December, once the tiers and voxel errors had made the
// views' working sets smaller (docs/out-of-core-rendering.md, "How a ray walks").
inline void lod_trace_stream(LodLane& lane, const Box3f& root_cell, const LodRay* rays, LodHit* hits, int n) {
    for (int i = 0; i < n; ++i) lod_traverse<false>(lane, root_cell, rays[i], hits[i]);
}

VASTRAY_KERNEL_END
