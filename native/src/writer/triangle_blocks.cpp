#include "writer/triangle_blocks.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

#include "writer/treelet.h"

namespace vastray::writer {

using format::kBlockSize;

std::pair<std::uint32_t, std::uint32_t> TriangleBlocks::add_leaf(const std::uint32_t* tris, std::uint32_t count,
                                                                 const TriangleSource& src) {
    constexpr std::uint32_t kWhole = 4096;
    // An empty leaf (the kd builder makes a few, e.g. where an empty-space cut leaves
    // nothing) reads nothing: a compact block spends no record on it.
    if (compact_ && count == 0) return {blocks_, 0};
    if (count <= kWhole) {
        std::uint32_t first = 0;
        if (add_whole(tris, count, src, first)) {
            open_leaves_.push_back({first, tris, count});
            return {blocks_, first};
        }
    } else {
        flush();
    }
    // Worst case for one more triangle: list entry, record, id, colour, 3 vertices. A
    // compact block can grow by more (wider fields for everything before it), which the
    // check after each insert catches.
    constexpr std::size_t kWorst = 2 + 6 + 4 + 4 + 36 + 8;
    const std::uint32_t start = blocks_;
    if (compact_) open_record();
    for (std::uint32_t i = 0; i < count; ++i) {
        if (size() + kWorst > kBlockSize) {
            flush();
            if (compact_) open_record();  // the leaf continues at the block's first record
        }
        const std::size_t list0 = list_.size(), tri0 = ids_.size(), vert0 = verts_.size();
        if (insert(tris + i, 1, src) && size() <= kBlockSize) continue;
        // The triangle pushed the block past 64 KiB after all: quantized vertices, a vertex
        // far from the others widened every vertex record; compact, any field widened.
        truncate(list0, tri0, vert0);
        flush();
        if (compact_) open_record();
        if (!insert(tris + i, 1, src)) throw std::logic_error("a triangle does not fit in an empty triangle block");
    }
    open_continues_ = true;
    if (compact_) close_record();
    return {start, compact_ ? static_cast<std::uint32_t>(format::compact::kHeader) : 0u};
}

bool TriangleBlocks::add_whole(const std::uint32_t* tris, std::uint32_t count, const TriangleSource& src,
                               std::uint32_t& first) {
    for (int attempt = 0; attempt < 2; ++attempt) {
        const std::size_t list0 = list_.size(), tri0 = ids_.size(), vert0 = verts_.size();
        first = static_cast<std::uint32_t>(compact_ ? format::compact::kHeader + closed_record_bytes_ : list0);
        if (compact_) open_record();
        if (insert(tris, count, src) && size() <= kBlockSize) {
            if (compact_) close_record();
            return true;
        }
        // Too full: close the block as it was before this leaf and try a fresh one.
        truncate(list0, tri0, vert0);
        if (attempt == 0) flush();
    }
    truncate(0, 0, 0);
    clear_maps();
    return false;
}

bool TriangleBlocks::take_open_leaves(std::vector<OpenLeaf>& out) {
    if (list_.empty()) return false;
    if (open_continues_) {
        flush();
        return false;
    }
    out = std::move(open_leaves_);
    clear_open();
    return true;
}

void TriangleBlocks::truncate(std::size_t list_size, std::size_t tris, std::size_t verts) {
    list_.resize(list_size);
    ids_.resize(tris);
    tri_verts_.resize(3 * tris);
    if (has_colours_) colours_.resize(tris);
    verts_.resize(verts);
    if (quantized_) {
        grid_.resize(verts);
        reset_span();
        for (const auto& k : grid_) extend_span(k);
    }
    if (!compact_) return;
    // Records, palette and groups follow from what is left (a truncation is always
    // followed by closing the block, so this runs once per block). A truncation cuts
    // where a leaf began, or inside the open record of a big leaf.
    while (!records_.empty() && records_.back().begin >= list_size) {
        records_.pop_back();
        record_open_ = false;
    }
    if (!records_.empty()) {  // an open record's end follows the list
        records_.back().end = record_open_ ? list_size : std::min(records_.back().end, list_size);
    }
    closed_record_bytes_ = 0;
    for (std::size_t r = 0; r + (record_open_ ? 1 : 0) < records_.size(); ++r) {
        closed_record_bytes_ += (replay(records_[r]).bits(records_[r].partial) + 7) / 8;
    }
    open_shape_ = record_open_ ? replay(records_.back()) : RecordShape{};
    if (has_colours_) {  // the palette is in order of first use
        palette_index_.resize(tris);
        std::uint32_t used = 0;
        for (std::uint32_t p : palette_index_) used = std::max(used, p + 1);
        palette_.resize(used);
    }
    closed_group_bytes_ = 0;
    block_ids_ = {};
    for (std::size_t t = 0; t < tris; ++t) add_to_group(t);
}

void TriangleBlocks::clear_maps() {
    id_map_.clear();
    vertex_map_.clear();
    if (compact_) palette_map_.clear();
}

void TriangleBlocks::reset_span() {
    k_lo_.fill(std::numeric_limits<std::int32_t>::max());
    k_hi_.fill(std::numeric_limits<std::int32_t>::min());
}

void TriangleBlocks::extend_span(const std::array<std::int32_t, 3>& k) {
    for (int a = 0; a < 3; ++a) {
        k_lo_[a] = std::min(k_lo_[a], k[a]);
        k_hi_[a] = std::max(k_hi_[a], k[a]);
    }
}

std::vector<std::uint8_t> TriangleBlocks::plain_bytes(const format::TriangleBlockLayout& l) const {
    std::vector<std::uint8_t> bytes(l.end, 0);
    const std::uint32_t header[4] = {static_cast<std::uint32_t>(list_.size()), static_cast<std::uint32_t>(ids_.size()),
                                     static_cast<std::uint32_t>(verts_.size()), packing()};
    std::memcpy(bytes.data(), header, sizeof header);
    std::memcpy(bytes.data() + l.list, list_.data(), 2 * list_.size());
    std::memcpy(bytes.data() + l.triangles, tri_verts_.data(), 2 * tri_verts_.size());
    std::memcpy(bytes.data() + l.ids, ids_.data(), 4 * ids_.size());
    if (has_colours_) std::memcpy(bytes.data() + l.colours, colours_.data(), 4 * colours_.size());
    if (l.packed) {
        std::memcpy(bytes.data() + l.vertices, k_lo_.data(), 12);
        std::uint8_t* at = bytes.data() + l.vertices + 12;
        for (const auto& k : grid_) {
            std::uint64_t w = 0;
            std::uint32_t shift = 0;
            for (int a = 0; a < 3; ++a) {
                w |= static_cast<std::uint64_t>(static_cast<std::uint32_t>(k[a] - k_lo_[a])) << shift;
                shift += l.bits[a];
            }
            std::memcpy(at, &w, l.record);
            at += l.record;
        }
    } else {
        std::memcpy(bytes.data() + l.vertices, verts_.data(), 12 * verts_.size());
    }
    return bytes;
}

void TriangleBlocks::flush() {
    if (list_.empty()) {
        // Nothing stored: an opened record with no entries goes too.
        records_.clear();
        record_open_ = false;
        return;
    }
    std::vector<std::uint8_t> bytes;
    if (compact_) {
        if (record_open_) {  // a big leaf goes on in the next block
            records_.back().partial = true;
            close_record();
        }
        bytes = compact_bytes();
        format::CompactTriangleBlock view{};
        if (!format::CompactTriangleBlock::parse(bytes.data(), bytes.size(), has_colours_, quantized_, view)) {
            throw std::logic_error("a compact triangle block does not parse");
        }
        stats_.vertex_bytes += view.end - view.vertices;
    } else {
        const format::TriangleBlockLayout l = layout();
        bytes = plain_bytes(l);
        stats_.vertex_bytes += l.end - l.vertices;
    }
    if (bytes.size() > kBlockSize) throw std::logic_error("a triangle block outgrew 64 KiB");
    stats_.stored_triangles += ids_.size();
    stats_.stored_vertices += verts_.size();
    stats_.triangle_blocks++;
    stats_.triangle_bytes += bytes.size();
    StreamStats& stream = triangle_stream(stats_, tier_);
    stream.blocks++;
    stream.bytes += bytes.size();
    stream.items += ids_.size();
    stream.extra += verts_.size();
    out_(-1, tier_, bytes);
    ++blocks_;
    clear_open();
}

void TriangleBlocks::clear_open() {
    list_.clear();
    ids_.clear();
    tri_verts_.clear();
    colours_.clear();
    verts_.clear();
    grid_.clear();
    reset_span();
    clear_maps();
    reset_compact();
    open_leaves_.clear();
    open_continues_ = false;
}

std::array<std::int32_t, 3> TriangleBlocks::grid_index(const Vec3f& p) const {
    std::array<std::int32_t, 3> k;
    for (int a = 0; a < 3; ++a) {
        const float q = p[a] / steps_[a];  // exact: the step is a power of two
        constexpr float kMax = static_cast<float>(1 << format::kVertexGridBits);
        if (!(std::abs(q) < kMax) || std::nearbyint(q) != q) {
            throw std::logic_error("a vertex is not on the quantized vertex grid");
        }
        k[a] = static_cast<std::int32_t>(q);
    }
    return k;
}

bool TriangleBlocks::insert(const std::uint32_t* tris, std::uint32_t count, const TriangleSource& src) {
    for (std::uint32_t i = 0; i < count; ++i) {
        // Past these counts no block can hold what is inserted: stop before the dedup
        // tables fill.
        if (verts_.size() > max_vertices_ || ids_.size() > max_triangles_) return false;
        const std::uint32_t t = tris[i];
        bool fresh = false;
        const std::uint32_t id = src.id(t);
        const std::uint32_t local = id_map_.find_or_insert(id, static_cast<std::uint32_t>(ids_.size()), fresh);
        if (compact_) {
            // The entry as its leaf record will hold it: a new triangle, or the distance
            // back from the newest one.
            ++open_shape_.entries;
            if (!fresh) {
                ++open_shape_.old;
                open_shape_.max_distance =
                    std::max(open_shape_.max_distance, static_cast<std::uint32_t>(ids_.size()) - 1 - local);
            }
        }
        if (fresh) {
            ids_.push_back(id);
            if (has_colours_) colours_.push_back(src.colour(t));
            const Vec3f* corners = src.corners(t);
            for (int k = 0; k < 3; ++k) {
                const Vec3f& p = corners[k];
                // Quantized: one vertex per grid point (+0 and -0 alike).
                std::array<std::int32_t, 3> g{};
                if (quantized_) g = grid_index(p);
                const VertexKey key = quantized_
                    ? VertexKey{{static_cast<std::uint32_t>(g[0]), static_cast<std::uint32_t>(g[1]), static_cast<std::uint32_t>(g[2])}}
                    : VertexKey{{format::float_bits(p.x), format::float_bits(p.y), format::float_bits(p.z)}};
                bool new_vertex = false;
                const std::uint32_t v = vertex_map_.find_or_insert(key, static_cast<std::uint32_t>(verts_.size()), new_vertex);
                if (new_vertex) {
                    if (quantized_) {
                        // Stored as k * step, the value every reader decodes (f32 blocks too).
                        verts_.push_back({format::grid_vertex(g[0], steps_.x), format::grid_vertex(g[1], steps_.y),
                                          format::grid_vertex(g[2], steps_.z)});
                        grid_.push_back(g);
                        extend_span(g);
                    } else {
                        verts_.push_back(p);
                    }
                }
                tri_verts_.push_back(static_cast<std::uint16_t>(v));
            }
            if (compact_) {
                if (has_colours_) {
                    bool new_colour = false;
                    const std::uint32_t c = src.colour(t);
                    const std::uint32_t p =
                        palette_map_.find_or_insert(c, static_cast<std::uint32_t>(palette_.size()), new_colour);
                    if (new_colour) palette_.push_back(c);
                    palette_index_.push_back(p);
                }
                add_to_group(ids_.size() - 1);
            }
        }
        list_.push_back(static_cast<std::uint16_t>(local));
    }
    return true;
}

// ---- compact blocks -------------------------------------------------------------------

void TriangleBlocks::open_record() {
    records_.push_back({list_.size(), list_.size(), static_cast<std::uint32_t>(ids_.size()), false});
    record_open_ = true;
    open_shape_ = {};
}

void TriangleBlocks::close_record() {
    records_.back().end = list_.size();
    record_open_ = false;
    closed_record_bytes_ += (open_shape_.bits(records_.back().partial) + 7) / 8;
    open_shape_ = {};
}

std::size_t TriangleBlocks::RecordShape::bits(bool partial) const {
    using namespace format::compact;
    return kBaseBits + kWidthBits + 1 + (partial ? kCountBits : 0) + entries + std::size_t{old} * format::bit_length(max_distance);
}

TriangleBlocks::RecordShape TriangleBlocks::replay(const Record& r) const {
    RecordShape s;
    std::uint32_t next = r.base;
    for (std::size_t e = r.begin; e < r.end; ++e) {
        ++s.entries;
        const std::uint32_t local = list_[e];
        if (local == next) {
            ++next;
        } else {
            ++s.old;
            s.max_distance = std::max(s.max_distance, next - 1 - local);
        }
    }
    return s;
}

std::size_t TriangleBlocks::IdCoding::bits(std::size_t n) const {
    return split ? format::compact::kIdWidthBits + distance_bits + n * (1 + width) : n * width;
}

TriangleBlocks::IdCoding TriangleBlocks::id_coding(const std::uint32_t* ids, std::size_t n) {
    using format::bit_length;
    std::array<std::uint32_t, format::compact::kGroup> s{};
    for (std::size_t i = 0; i < n; ++i) {  // insertion sort: a group holds at most kGroup
        std::size_t k = i;
        for (; k > 0 && s[k - 1] > ids[i]; --k) s[k] = s[k - 1];
        s[k] = ids[i];
    }
    IdCoding c;
    c.base = s[0];
    c.width = bit_length(s[n - 1] - s[0]);
    // Two bases pay for a group whose triangles come from two runs of ids far apart
    // (neighbouring leaves of different parts or scan passes): split where that costs
    // the fewest bits, if fewer than one base.
    std::size_t best = c.bits(n);
    for (std::size_t cut = 1; cut < n; ++cut) {
        IdCoding two;
        two.base = s[0];
        two.split = true;
        two.second = s[cut];
        two.width = std::max(bit_length(s[cut - 1] - s[0]), bit_length(s[n - 1] - s[cut]));
        two.distance_bits = bit_length(s[cut] - s[0]);
        if (two.bits(n) < best) {
            best = two.bits(n);
            c = two;
        }
    }
    return c;
}

TriangleBlocks::GroupShape TriangleBlocks::group_shape(std::size_t first, std::size_t n) const {
    GroupShape g;
    g.n = n;
    for (std::size_t t = first; t < first + n; ++t) {
        for (int k = 0; k < 3; ++k) g.corners.add(tri_verts_[3 * t + static_cast<std::size_t>(k)]);
        if (has_colours_) g.palette.add(palette_index_[t]);
    }
    if (n > 0) g.ids = id_coding(ids_.data() + first, n);
    return g;
}

std::size_t TriangleBlocks::GroupShape::bits() const {
    return n * (3 * corners.width() + palette.width()) + (n > 0 ? ids.bits(n) : 0);
}

void TriangleBlocks::add_to_group(std::size_t t) {
    block_ids_.add(ids_[t]);
    if ((t + 1) % format::compact::kGroup == 0) {  // a group is full: its record is final
        const std::size_t first = t + 1 - format::compact::kGroup;
        closed_group_bytes_ += (group_shape(first, format::compact::kGroup).bits() + 7) / 8;
    }
}

std::size_t TriangleBlocks::compact_size() const {
    using format::CompactTriangleBlock;
    const std::size_t groups = CompactTriangleBlock::group_count(ids_.size());
    const std::uint32_t header = CompactTriangleBlock::header_width(
        static_cast<std::uint32_t>(verts_.size()), block_ids_.width(), has_colours_, static_cast<std::uint32_t>(palette_.size()));
    const std::size_t open = ids_.size() % format::compact::kGroup;
    const std::size_t data = closed_group_bytes_ + (group_shape(ids_.size() - open, open).bits() + 7) / 8;
    // An open record may yet continue in the next block: count its entry count too.
    const std::size_t records = closed_record_bytes_ + (record_open_ ? (open_shape_.bits(true) + 7) / 8 : 0);
    const std::uint32_t record_bits = quantized_ ? [&] {
        const std::uint32_t p = packing();
        return (p & 0xffu) + ((p >> 8) & 0xffu) + (p >> 16);
    }() : 0u;
    return format::compact::kHeader + records + (groups * header + 7) / 8 + data + 4 * palette_.size() +
           CompactTriangleBlock::vertex_bytes(verts_.size(), quantized_, record_bits);
}

std::vector<std::uint8_t> TriangleBlocks::compact_bytes() const {
    using namespace format;
    std::vector<std::uint8_t> out(compact::kHeader, 0);
    out.reserve(kBlockSize);
    for (const Record& r : records_) {
        const RecordShape s = replay(r);
        const std::uint32_t width = bit_length(s.max_distance);
        BitWriter bits(out);
        bits.put(r.base, compact::kBaseBits);
        bits.put(width, compact::kWidthBits);
        bits.put(r.partial ? 1 : 0, 1);
        if (r.partial) bits.put(s.entries, compact::kCountBits);
        std::uint32_t next = r.base;
        for (std::size_t e = r.begin; e < r.end; ++e) {
            const std::uint32_t local = list_[e];
            if (local == next) {
                bits.put(1, 1);
                ++next;
            } else {
                bits.put(0, 1);
                bits.put(next - 1 - local, width);
            }
        }
    }
    // Group headers first (fixed width, so a reader finds one from the group's index),
    // then each group's data record; the headers need the records' offsets, so the
    // records go to a buffer of their own first.
    const std::size_t groups_at = out.size();
    const std::size_t groups = CompactTriangleBlock::group_count(ids_.size());
    const std::uint32_t vertex_bits = bit_length(verts_.size() - 1);
    const std::uint32_t id_bits = block_ids_.width();
    const std::uint32_t palette_bits = has_colours_ ? bit_length(palette_.size() - 1) : 0;
    std::vector<std::uint8_t> data;
    {
        BitWriter headers(out);
        for (std::size_t j = 0; j < groups; ++j) {
            const std::size_t first = compact::kGroup * j, last = std::min(first + compact::kGroup, ids_.size());
            const GroupShape g = group_shape(first, last - first);
            if (data.size() > 0xffff) throw std::logic_error("compact triangle group offset overflow");
            headers.put(data.size(), 16);
            headers.put(g.corners.lo, vertex_bits);
            headers.put(g.corners.width(), compact::kWidthBits);
            headers.put(g.ids.base - block_ids_.lo, id_bits);
            headers.put(g.ids.width, compact::kIdWidthBits);
            headers.put(g.ids.split ? 1 : 0, 1);
            if (has_colours_) {
                headers.put(g.palette.lo, palette_bits);
                headers.put(g.palette.width(), compact::kWidthBits);
            }
            BitWriter bits(data);
            for (std::size_t t = first; t < last; ++t) {
                for (int k = 0; k < 3; ++k) bits.put(tri_verts_[3 * t + static_cast<std::size_t>(k)] - g.corners.lo, g.corners.width());
            }
            if (g.ids.split) {
                bits.put(g.ids.distance_bits, compact::kIdWidthBits);
                bits.put(g.ids.second - g.ids.base, g.ids.distance_bits);
                for (std::size_t t = first; t < last; ++t) {
                    const bool second = ids_[t] >= g.ids.second;
                    const std::uint64_t offset = ids_[t] - (second ? g.ids.second : g.ids.base);
                    bits.put(offset << 1 | (second ? 1u : 0u), 1 + g.ids.width);
                }
            } else {
                for (std::size_t t = first; t < last; ++t) bits.put(ids_[t] - g.ids.base, g.ids.width);
            }
            if (has_colours_) {
                for (std::size_t t = first; t < last; ++t) bits.put(palette_index_[t] - g.palette.lo, g.palette.width());
            }
        }
    }
    out.insert(out.end(), data.begin(), data.end());
    const std::size_t palette_at = out.size();
    for (std::uint32_t c : palette_) {
        out.resize(out.size() + 4);
        std::memcpy(out.data() + out.size() - 4, &c, 4);
    }
    const std::uint32_t pack = packing();
    if (quantized_) {
        out.resize(out.size() + 12);
        std::memcpy(out.data() + out.size() - 12, k_lo_.data(), 12);
        {
            BitWriter bits(out);
            for (const auto& k : grid_) {
                for (int a = 0; a < 3; ++a) {
                    bits.put(static_cast<std::uint32_t>(k[a] - k_lo_[a]), (pack >> (8 * a)) & 0xffu);
                }
            }
        }
        out.resize(out.size() + 8, 0);  // slack: readers load 8 bytes at a record
    } else {
        out.resize(out.size() + 12 * verts_.size());
        std::memcpy(out.data() + out.size() - 12 * verts_.size(), verts_.data(), 12 * verts_.size());
    }
    const std::uint32_t header[8] = {static_cast<std::uint32_t>(ids_.size()), static_cast<std::uint32_t>(verts_.size()),
                                     pack, static_cast<std::uint32_t>(palette_.size()), block_ids_.lo, id_bits,
                                     static_cast<std::uint32_t>(groups_at), static_cast<std::uint32_t>(palette_at)};
    std::memcpy(out.data(), header, sizeof header);
    if (out.size() != compact_size()) throw std::logic_error("compact triangle block size estimate is off");
    return out;
}

void TriangleBlocks::reset_compact() {
    records_.clear();
    record_open_ = false;
    closed_record_bytes_ = 0;
    open_shape_ = {};
    palette_.clear();
    palette_index_.clear();
    closed_group_bytes_ = 0;
    block_ids_ = {};
}

}  // namespace vastray::writer
