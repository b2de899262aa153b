#include "vastray/model_writer.h"

#include "vastray/thread_pool.h"

#include <chrono>
#include <mutex>
#include <stdexcept>
#include <string>
#include <utility>

namespace vastray {

using namespace format;

namespace {

// Face f = 2 * axis + side: side 0 is the face at the low end of the axis (looked at
// from -axis), side 1 the high one. A sample for face f describes what a viewer outside
// that face sees, so its normal is oriented towards the viewer (dot(n, outward_f) >= 0).
Vec3f outward(int f) {
    Vec3f o;
    o[f / 2] = (f % 2) != 0 ? 1.0f : -1.0f;
    return o;
}

struct FaceSamples {
    Vec3f colour[6];
    Vec3f normal[6];
};

// What a finished treelet looks like to the LOD node above it: its voxels and leaves as
// boxes with per-face samples. Voxels are sampled against these, one level finer.
struct Proxy {
    Box3f box;
    FaceSamples s;
};

// A reference that the merge of a part emitted in parallel must resolve. unit < 0: the
// u32 at `offset` is a triangle block id local to the part. unit >= 0: `offset` is a LOD
// node whose child treelets are the part's placement unit `unit`, not yet in a block.
struct Patch {
    std::uint32_t offset;
    int unit;
};

struct Pending {
    std::vector<std::uint8_t> bytes;  // the serialised treelet, a multiple of 8 bytes
    std::vector<Proxy> proxies;
    std::vector<Patch> patches;
};

// Where finished blocks go: straight to the sink, or into a buffer for a later merge.
using Emit = std::function<void(int level, std::vector<std::uint8_t>&& bytes)>;

struct LocalNode {
    enum Kind { Basic, Lod, Leaf } kind = Basic;
    int axis = 0;
    float split = 0;
    Box3f cell;
    std::uint32_t empty = 0;
    int left = -1, right = -1;              // basic: local indices of the children
    std::uint32_t kd_left = 0, kd_right = 0;  // LOD (in-core): kd-tree indices of the children
    int child_handles[2] = {-1, -1};        // LOD (out of core): pending children
    float radius = 0;
    std::uint32_t child_block = 0, child_off8 = 0, right_from_left8 = 0;
    std::uint32_t samples[6] = {};
    int sample_count = 0;
    std::uint32_t kd_node = 0;              // leaf (in-core): its kd node
    std::uint32_t tri_block = 0, first = 0, count = 0;
    int unit = -1;                          // LOD (deferred placement): the children's unit
    std::size_t offset = 0;
};

Box3f child_cell(const Box3f& cell, int axis, float split, int side) {
    Box3f c = cell;
    (side == 0 ? c.hi : c.lo)[axis] = split;
    return c;
}

// Open addressing for the per-block dedup tables (at most a few thousand entries, so
// a fixed table cleared through its used-slot list beats a node-based map).
template <typename Key, typename Hash>
class SmallMap {
public:
    explicit SmallMap(std::size_t capacity_log2 = 15)
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
using VertexKey = std::array<std::uint32_t, 3>;
struct VertexHash {
    std::size_t operator()(const VertexKey& k) const {
        std::uint64_t h = k[0] * 0x9E3779B97F4A7C15ull;
        h ^= (h >> 29) + k[1] * 0xBF58476D1CE4E5B9ull;
        h ^= (h >> 31) + k[2] * 0x94D049BB133111EBull;
        return static_cast<std::size_t>(h ^ (h >> 32));
    }
};

// Packs leaf triangle lists into triangle blocks: a list section pointing at triangle
// records, which point at vertices shared within the block (paper 000 §4.6).
class TriangleBlocks {
public:
    TriangleBlocks(bool has_colours, Emit& emit, ModelWriterStats& stats)
        : has_colours_(has_colours), emit_(emit), stats_(stats) {}

    // Adds one leaf's triangles (soup indices); returns (block id, first list entry).
    std::uint32_t blocks() const { return blocks_; }
    // A triangle block emitted elsewhere took the next id (parallel merge).
    void skip_block() { ++blocks_; }

    // A leaf's list normally lies in one block. A leaf too big for one (a fan of
    // thousands of triangles around a vertex, which no split can separate) continues
    // at entry 0 of the following triangle blocks.
    std::pair<std::uint32_t, std::uint32_t> add_leaf(const std::uint32_t* tris, std::uint32_t count,
                                                     const Vec3f* corners, const std::uint32_t* ids,
                                                     const std::uint32_t* colours) {
        // Bounded so the dedup tables (32768 slots) never fill: 3 vertices per triangle.
        constexpr std::uint32_t kWhole = 4096;
        if (count <= kWhole) {
            const std::size_t list0 = list_.size(), tri0 = ids_.size(), vert0 = verts_.size();
            insert(tris, count, corners, ids, colours);
            if (layout().end <= kBlockSize) return {blocks_, static_cast<std::uint32_t>(list0)};
            // Too full: close the block as it was before this leaf and try a fresh one.
            truncate(list0, tri0, vert0);
            flush();
            insert(tris, count, corners, ids, colours);
            if (layout().end <= kBlockSize) return {blocks_, 0};
            truncate(0, 0, 0);
            id_map_.clear();
            vertex_map_.clear();
        } else {
            flush();
        }
        // Worst case for one more triangle: list entry, record, id, colour, 3 vertices.
        constexpr std::size_t kWorst = 2 + 6 + 4 + 4 + 36 + 8;
        const std::uint32_t start = blocks_;
        for (std::uint32_t i = 0; i < count; ++i) {
            if (layout().end + kWorst > kBlockSize) flush();
            insert(tris + i, 1, corners, ids, colours);
        }
        return {start, 0};
    }

    void truncate(std::size_t list_size, std::size_t tris, std::size_t verts) {
        list_.resize(list_size);
        ids_.resize(tris);
        tri_verts_.resize(3 * tris);
        if (has_colours_) colours_.resize(tris);
        verts_.resize(verts);
    }

    void flush() {
        if (list_.empty()) return;
        const TriangleBlockLayout l = layout();
        std::vector<std::uint8_t> out(l.end, 0);
        const std::uint32_t header[4] = {static_cast<std::uint32_t>(list_.size()),
                                         static_cast<std::uint32_t>(ids_.size()),
                                         static_cast<std::uint32_t>(verts_.size()), 0};
        std::memcpy(out.data(), header, sizeof header);
        std::memcpy(out.data() + l.list, list_.data(), 2 * list_.size());
        std::memcpy(out.data() + l.triangles, tri_verts_.data(), 2 * tri_verts_.size());
        std::memcpy(out.data() + l.ids, ids_.data(), 4 * ids_.size());
        if (has_colours_) std::memcpy(out.data() + l.colours, colours_.data(), 4 * colours_.size());
        std::memcpy(out.data() + l.vertices, verts_.data(), 12 * verts_.size());
        stats_.stored_triangles += ids_.size();
        stats_.stored_vertices += verts_.size();
        stats_.triangle_blocks++;
        stats_.triangle_bytes += out.size();
        emit_(-1, std::move(out));
        ++blocks_;
        list_.clear();
        ids_.clear();
        tri_verts_.clear();
        colours_.clear();
        verts_.clear();
        id_map_.clear();
        vertex_map_.clear();
    }

private:
    TriangleBlockLayout layout() const {
        return TriangleBlockLayout::of(list_.size(), ids_.size(), verts_.size(), has_colours_);
    }

    void insert(const std::uint32_t* tris, std::uint32_t count, const Vec3f* corners,
                const std::uint32_t* ids, const std::uint32_t* colours) {
        for (std::uint32_t i = 0; i < count; ++i) {
            const std::uint32_t t = tris[i];
            bool fresh = false;
            const std::uint32_t local = id_map_.find_or_insert(ids[t], static_cast<std::uint32_t>(ids_.size()), fresh);
            if (fresh) {
                ids_.push_back(ids[t]);
                if (has_colours_) colours_.push_back(colours[t]);
                for (int k = 0; k < 3; ++k) {
                    const Vec3f& p = corners[3 * static_cast<std::size_t>(t) + static_cast<std::size_t>(k)];
                    const VertexKey key{float_bits(p.x), float_bits(p.y), float_bits(p.z)};
                    bool new_vertex = false;
                    const std::uint32_t v =
                        vertex_map_.find_or_insert(key, static_cast<std::uint32_t>(verts_.size()), new_vertex);
                    if (new_vertex) verts_.push_back(p);
                    tri_verts_.push_back(static_cast<std::uint16_t>(v));
                }
            }
            list_.push_back(static_cast<std::uint16_t>(local));
        }
    }

    bool has_colours_;
    Emit& emit_;
    ModelWriterStats& stats_;
    std::uint32_t blocks_ = 0;
    std::vector<std::uint16_t> list_, tri_verts_;
    std::vector<std::uint32_t> ids_, colours_;
    std::vector<Vec3f> verts_;
    SmallMap<std::uint32_t, IdHash> id_map_;
    SmallMap<VertexKey, VertexHash> vertex_map_;
};

// Leaf references written so far, shared by the emitters of one writer (progress bars).
struct ProgressCounter {
    ProgressSink sink;
    std::mutex mutex;
    std::uint64_t references = 0, reported = 0;

    void add(std::uint64_t n) {
        std::lock_guard<std::mutex> lock(mutex);
        references += n;
        if (sink && references - reported >= (1u << 16)) {
            reported = references;
            sink(references);
        }
    }
};


// Sibling treelets a deferred emitter would have placed in a block of `level`.
struct Unit {
    std::size_t level;
    Pending data;
};

// Emits treelets and triangle blocks into one set of level streams. The writer has a
// main emitter that feeds the sink. Parts of a subtree emitted in parallel get their
// own, which defer placing treelets (they record placement units instead) and buffer
// their triangle blocks; the main emitter merges them in order, packing the units into
// its own blocks, so nodes pack exactly as if one thread had emitted everything.
struct Emitter {
    const ModelWriterParams& p;
    ProgressCounter& counter;
    ModelWriterStats stats;
    Emit emit;
    std::vector<std::vector<std::uint8_t>> level_buf;
    TriangleBlocks triangles;
    bool defer = false;
    std::vector<Unit> units;

    // The subtree being emitted.
    const KdTree* tree = nullptr;
    const Vec3f* corners = nullptr;
    const std::uint32_t* ids = nullptr;
    const std::uint32_t* colours = nullptr;

    Emitter(const ModelWriterParams& params, ProgressCounter& c, Emit e)
        : p(params), counter(c), emit(std::move(e)), triangles(params.has_colours, emit, stats) {}

    void ensure_level(std::size_t level) {
        if (level_buf.size() > level) return;
        level_buf.resize(level + 1);
        stats.level_blocks.resize(level + 1, 0);
        stats.level_bytes.resize(level + 1, 0);
        stats.level_nodes.resize(level + 1, 0);
        stats.level_voxels.resize(level + 1, 0);
    }

    void flush_level(std::size_t level) {
        if (level >= level_buf.size()) return;
        auto& buf = level_buf[level];
        if (buf.empty()) return;
        stats.level_blocks[level]++;
        stats.level_bytes[level] += buf.size();
        emit(static_cast<int>(level), std::move(buf));
        buf.clear();
    }

    // Places sibling treelets contiguously in one block of `level`; returns the block id
    // and the first one's offset.
    std::pair<std::uint32_t, std::size_t> place(std::size_t level, const Pending* a, const Pending* b) {
        ensure_level(level);
        auto& buf = level_buf[level];
        const std::size_t need = (a ? a->bytes.size() : 0) + (b ? b->bytes.size() : 0);
        if (buf.size() + need > kBlockSize) flush_level(level);
        const std::size_t off = buf.size();
        // (Patches are for deferred parts only; here every id is final.)
        for (const Pending* t : {a, b}) {
            if (t != nullptr) buf.insert(buf.end(), t->bytes.begin(), t->bytes.end());
        }
        stats.treelets += (a ? 1 : 0) + (b ? 1 : 0);
        return {static_cast<std::uint32_t>(stats.level_blocks[level]), off};
    }

    // ---- voxels ------------------------------------------------------------------------

    // Orthographic rays from each face of the cell into the finished level below: the
    // nearest proxy along each ray is what a viewer on that side sees there.
    FaceSamples sample_voxel(const Box3f& cell, const Pending* a, const Pending* b) const {
        FaceSamples out;
        bool have[6] = {};
        const int k = std::clamp(p.voxel_rays_per_axis, 1, 8);
        std::vector<const Proxy*> proxies;
        proxies.reserve(16);
        for (const Pending* t : {a, b}) {
            if (t == nullptr) continue;
            for (const Proxy& q : t->proxies) proxies.push_back(&q);
        }
        const Proxy* hit[64];
        float depth[64];
        for (int f = 0; f < 6; ++f) {
            const int axis = f / 2, side = f % 2, u = (axis + 1) % 3, v = (axis + 2) % 3;
            const float du = (cell.hi[u] - cell.lo[u]) / static_cast<float>(k);
            const float dv = (cell.hi[v] - cell.lo[v]) / static_cast<float>(k);
            std::fill(hit, hit + k * k, nullptr);
            std::fill(depth, depth + k * k, std::numeric_limits<float>::infinity());
            // Ray (i, j) passes through (lo + (i + 0.5) du, lo + (j + 0.5) dv): each proxy
            // covers a rectangle of rays, found by arithmetic instead of testing each ray.
            auto range = [k](float lo, float hi, float origin, float step, int& first, int& last) {
                if (!(step > 0)) {
                    first = 0;
                    last = lo <= origin && origin <= hi ? k - 1 : -1;
                    return;
                }
                first = std::max(0, static_cast<int>(std::ceil((lo - origin) / step - 0.5f)));
                last = std::min(k - 1, static_cast<int>(std::floor((hi - origin) / step - 0.5f)));
            };
            for (const Proxy* q : proxies) {
                int i0, i1, j0, j1;
                range(q->box.lo[u], q->box.hi[u], cell.lo[u], du, i0, i1);
                range(q->box.lo[v], q->box.hi[v], cell.lo[v], dv, j0, j1);
                const float d = side == 0 ? q->box.lo[axis] : -q->box.hi[axis];
                for (int i = i0; i <= i1; ++i) {
                    for (int j = j0; j <= j1; ++j) {
                        if (d < depth[i * k + j]) {
                            depth[i * k + j] = d;
                            hit[i * k + j] = q;
                        }
                    }
                }
            }
            Vec3f colour, normal;
            int hits = 0;
            for (int r = 0; r < k * k; ++r) {
                if (hit[r] == nullptr) continue;
                colour += hit[r]->s.colour[f];
                normal += hit[r]->s.normal[f];
                ++hits;
            }
            if (hits > 0 && dot(normal, normal) > 0) {
                out.colour[f] = colour / static_cast<float>(hits);
                out.normal[f] = normalize(normal);
                have[f] = true;
            }
        }
        // Faces no ray saw anything through (thin geometry between the rays) borrow from
        // the faces that did, or from every proxy when none did.
        Vec3f colour_sum, normal_sum;
        int seen = 0;
        for (int f = 0; f < 6; ++f) {
            if (!have[f]) continue;
            colour_sum += out.colour[f];
            ++seen;
        }
        if (seen == 0) {
            int n = 0;
            for (const Pending* t : {a, b}) {
                if (t == nullptr) continue;
                for (const Proxy& q : t->proxies) {
                    for (int f = 0; f < 6; ++f) colour_sum += q.s.colour[f];
                    n += 6;
                }
            }
            colour_sum = n > 0 ? colour_sum / static_cast<float>(n) : Vec3f(0.75f, 0.75f, 0.75f);
        } else {
            colour_sum = colour_sum / static_cast<float>(seen);
        }
        for (int f = 0; f < 6; ++f) {
            if (have[f]) continue;
            const Vec3f o = outward(f);
            normal_sum = Vec3f();
            for (int g = 0; g < 6; ++g) {
                if (have[g]) normal_sum += out.normal[g] * (dot(out.normal[g], o) < 0 ? -1.0f : 1.0f);
            }
            out.colour[f] = colour_sum;
            out.normal[f] = dot(normal_sum, normal_sum) > 0 ? normalize(normal_sum) : o;
        }
        return out;
    }

    // Quantises the six samples, collapsing them to one when they agree (normals up to
    // sign: shading is two-sided). Returns the samples the level above will see.
    FaceSamples store_voxel(const FaceSamples& s, LocalNode& node) {
        Vec3f cm, nm;
        for (int f = 0; f < 6; ++f) {
            cm += s.colour[f];
            nm += s.normal[f] * (dot(s.normal[f], s.normal[0]) < 0 ? -1.0f : 1.0f);
        }
        cm = cm / 6.0f;
        nm = dot(nm, nm) > 0 ? normalize(nm) : s.normal[0];
        bool one = true;
        for (int f = 0; f < 6 && one; ++f) {
            const Vec3f n = s.normal[f] * (dot(s.normal[f], nm) < 0 ? -1.0f : 1.0f);
            for (int c = 0; c < 3; ++c) {
                if (std::abs(s.colour[f][c] - cm[c]) > p.one_sample_colour ||
                    std::abs(n[c] - nm[c]) > p.one_sample_normal) {
                    one = false;
                }
            }
        }
        FaceSamples seen = s;
        if (one) {
            node.samples[0] = pack_sample(cm, nm, true);
            node.sample_count = 1;
            stats.voxels_one++;
            for (int f = 0; f < 6; ++f) {
                seen.colour[f] = cm;
                seen.normal[f] = nm * (dot(nm, outward(f)) < 0 ? -1.0f : 1.0f);
            }
        } else {
            for (int f = 0; f < 6; ++f) node.samples[f] = pack_sample(s.colour[f], s.normal[f], false);
            node.sample_count = 6;
            stats.voxels_six++;
        }
        return seen;
    }

    Proxy leaf_proxy(const std::uint32_t* tris, std::uint32_t count, const Box3f& cell) const {
        Proxy q;
        Vec3f csum[6], nsum[6];
        float wsum[6] = {}, area_sum = 0;
        Vec3f cflat, nflat, first_normal;
        for (std::uint32_t i = 0; i < count; ++i) {
            const Vec3f* v = corners + 3 * static_cast<std::size_t>(tris[i]);
            for (int k = 0; k < 3; ++k) q.box.extend(v[k]);
            Vec3f n = cross(v[1] - v[0], v[2] - v[0]);
            const float area = 0.5f * length(n);
            if (!(area > 0)) continue;
            n = n / (2.0f * area);
            Vec3f c(0.75f, 0.75f, 0.75f);
            if (colours != nullptr) {
                const std::uint32_t rgb = colours[tris[i]];
                c = Vec3f(static_cast<float>(rgb & 255u), static_cast<float>((rgb >> 8) & 255u),
                          static_cast<float>((rgb >> 16) & 255u)) / 255.0f;
            }
            cflat += c * area;
            area_sum += area;
            // Unoriented mean normal (signs aligned to the first triangle), for faces that
            // see the leaf edge-on.
            if (dot(first_normal, first_normal) == 0) first_normal = n;
            nflat += n * (dot(n, first_normal) < 0 ? -area : area);
            for (int f = 0; f < 6; ++f) {
                // Weighted by the area seen from face f, oriented towards that viewer.
                const float proj = dot(n, outward(f));
                const float w = area * std::abs(proj);
                csum[f] += c * w;
                nsum[f] += n * (proj < 0 ? -w : w);
                wsum[f] += w;
            }
        }
        q.box = Box3f::intersection(q.box, cell);
        if (q.box.empty()) q.box = cell;
        const Vec3f grey(0.75f, 0.75f, 0.75f);
        for (int f = 0; f < 6; ++f) {
            if (wsum[f] > 0 && dot(nsum[f], nsum[f]) > 0) {
                q.s.colour[f] = csum[f] / wsum[f];
                q.s.normal[f] = normalize(nsum[f]);
            } else {
                // Edge-on (every triangle parallel to the view): the surface normal still
                // says how the leaf shades from nearby directions.
                q.s.colour[f] = area_sum > 0 ? cflat / area_sum : grey;
                const Vec3f o = outward(f);
                const float side = dot(nflat, o) < 0 ? -1.0f : 1.0f;
                q.s.normal[f] = dot(nflat, nflat) > 0 ? normalize(nflat) * side : o;
            }
        }
        return q;
    }

    // ---- treelets ----------------------------------------------------------------------

    // Finishes a LOD node whose children are finished: samples its voxel, places the
    // children side by side one level down, and records where they went.
    void finish_lod(LocalNode& node, Pending* a, Pending* b, std::size_t level, Pending& self) {
        const FaceSamples s = sample_voxel(node.cell, a, b);
        const FaceSamples seen = store_voxel(s, node);
        self.proxies.push_back({node.cell, seen});
        if (defer) {
            Unit u{level + 1, {}};
            for (const Pending* t : {a, b}) {
                if (t == nullptr) continue;
                for (const Patch& q : t->patches) {
                    u.data.patches.push_back({static_cast<std::uint32_t>(u.data.bytes.size()) + q.offset, q.unit});
                }
                u.data.bytes.insert(u.data.bytes.end(), t->bytes.begin(), t->bytes.end());
            }
            node.unit = static_cast<int>(units.size());
            units.push_back(std::move(u));
        } else {
            const auto [block, off] = place(level + 1, a, b);
            node.child_block = block;
            node.child_off8 = static_cast<std::uint32_t>(off / 8);
        }
        node.right_from_left8 = a != nullptr && b != nullptr ? static_cast<std::uint32_t>(a->bytes.size() / 8) : 0;
        const Vec3f e = node.cell.extent();
        node.radius = 0.5f * length(e);
    }

    // Lays out a finished treelet; every node passes here once, so the node statistics
    // are kept here too.
    void serialise(std::vector<LocalNode>& nodes, std::size_t level, Pending& out) {
        ensure_level(level);
        stats.level_nodes[level] += nodes.size();
        std::size_t cursor = 0;
        for (LocalNode& n : nodes) {
            n.offset = cursor;
            cursor += n.kind == LocalNode::Lod ? 16 : 8;
            std::uint64_t& kind_count = n.kind == LocalNode::Lod    ? stats.lod_nodes
                                        : n.kind == LocalNode::Leaf ? stats.leaves
                                                                    : stats.basic_nodes;
            ++kind_count;
            stats.empty_children += (n.empty & kLeftEmpty ? 1 : 0) + (n.empty & kRightEmpty ? 1 : 0);
        }
        std::vector<std::size_t> voxel_at(nodes.size(), 0);
        for (std::size_t i = 0; i < nodes.size(); ++i) {
            if (nodes[i].kind != LocalNode::Lod) continue;
            voxel_at[i] = cursor;
            cursor += 4 * static_cast<std::size_t>(nodes[i].sample_count);
        }
        cursor = (cursor + 7) & ~std::size_t{7};
        out.bytes.assign(cursor, 0);
        auto put = [&](std::size_t at, std::uint32_t w) { std::memcpy(out.bytes.data() + at, &w, 4); };
        for (std::size_t i = 0; i < nodes.size(); ++i) {
            const LocalNode& n = nodes[i];
            switch (n.kind) {
                case LocalNode::Basic: {
                    const std::uint32_t right8 =
                        n.right >= 0 ? static_cast<std::uint32_t>((nodes[static_cast<std::size_t>(n.right)].offset - n.offset) / 8) : 0;
                    put(n.offset, basic_word(n.axis, n.empty, right8));
                    put(n.offset + 4, float_bits(n.split));
                    break;
                }
                case LocalNode::Lod: {
                    stats.level_voxels[level]++;
                    const auto voxel4 = static_cast<std::uint32_t>((voxel_at[i] - n.offset) / 4);
                    if (voxel4 > 127 || n.right_from_left8 > 63 || n.child_off8 > 8191) {
                        throw std::logic_error("LOD node field overflow");
                    }
                    put(n.offset, lod_word(n.axis, n.empty, voxel4, n.right_from_left8, n.child_off8));
                    put(n.offset + 4, float_bits(n.split));
                    put(n.offset + 8, float_bits(n.radius));
                    put(n.offset + 12, n.child_block);
                    if (n.unit >= 0) out.patches.push_back({static_cast<std::uint32_t>(n.offset), n.unit});
                    for (int s = 0; s < n.sample_count; ++s) put(voxel_at[i] + 4 * static_cast<std::size_t>(s), n.samples[s]);
                    break;
                }
                case LocalNode::Leaf:
                    put(n.offset, leaf_word(n.first, n.count));
                    put(n.offset + 4, n.tri_block);
                    out.patches.push_back({static_cast<std::uint32_t>(n.offset + 4), -1});
                    break;
            }
        }
    }

    void collect_kd(std::uint32_t index, const Box3f& cell, int depth, std::vector<LocalNode>& nodes) {
        const KdNode& k = tree->nodes[index];
        LocalNode n;
        n.cell = cell;
        if (k.is_leaf()) {
            n.kind = LocalNode::Leaf;
            n.kd_node = index;
            nodes.push_back(n);
            return;
        }
        n.axis = k.axis();
        n.split = k.split();
        n.empty = (k.left_empty() ? kLeftEmpty : 0u) | (k.right_empty() ? kRightEmpty : 0u);
        const std::uint32_t left = index + 1, right = index + k.right_offset();
        if (depth == kTreeletHeight - 1) {
            n.kind = LocalNode::Lod;
            n.kd_left = left;
            n.kd_right = right;
            nodes.push_back(n);
            return;
        }
        const std::size_t self = nodes.size();
        nodes.push_back(n);
        if (!k.left_empty()) {
            nodes[self].left = static_cast<int>(nodes.size());
            collect_kd(left, child_cell(cell, n.axis, n.split, 0), depth + 1, nodes);
        }
        if (!k.right_empty()) {
            nodes[self].right = static_cast<int>(nodes.size());
            collect_kd(right, child_cell(cell, n.axis, n.split, 1), depth + 1, nodes);
        }
    }

    // Emits the treelet rooted at kd node `root` and everything below it. `children`,
    // when given, holds its LOD nodes' child treelets already emitted (in order).
    Pending emit_kd_treelet(std::uint32_t root, const Box3f& cell, std::size_t level,
                            std::vector<Pending>* children = nullptr) {
        std::vector<LocalNode> nodes;
        nodes.reserve(7);
        collect_kd(root, cell, 0, nodes);
        Pending self;
        std::size_t next_child = 0;
        for (LocalNode& n : nodes) {
            if (n.kind == LocalNode::Lod) {
                const bool has_l = (n.empty & kLeftEmpty) == 0, has_r = (n.empty & kRightEmpty) == 0;
                Pending l, r;
                if (children != nullptr) {
                    if (has_l) l = std::move((*children)[next_child++]);
                    if (has_r) r = std::move((*children)[next_child++]);
                } else {
                    if (has_l) l = emit_kd_treelet(n.kd_left, child_cell(n.cell, n.axis, n.split, 0), level + 1);
                    if (has_r) r = emit_kd_treelet(n.kd_right, child_cell(n.cell, n.axis, n.split, 1), level + 1);
                }
                finish_lod(n, has_l ? &l : nullptr, has_r ? &r : nullptr, level, self);
            } else if (n.kind == LocalNode::Leaf) {
                const KdNode& k = tree->nodes[n.kd_node];
                const std::uint32_t* tris = tree->tri_ids.data() + k.first();
                n.count = k.count();
                if (n.count > kMaxLeafTriangles) throw std::length_error("kd-tree leaf too large for the format");
                const auto [block, first] = triangles.add_leaf(tris, n.count, corners, ids, colours);
                n.tri_block = block;
                n.first = first;
                self.proxies.push_back(leaf_proxy(tris, n.count, n.cell));
                stats.references += n.count;
                counter.add(n.count);
            }
        }
        serialise(nodes, level, self);
        return self;
    }

    // Appends a triangle block a parallel part made: it takes the next triangle block id.
    void adopt_triangle_block(std::vector<std::uint8_t>&& bytes) {
        stats.triangle_blocks++;
        stats.triangle_bytes += bytes.size();
        triangles.skip_block();
        emit(-1, std::move(bytes));
    }

    // Moves a part emitted in parallel into these streams: its triangle blocks follow
    // ours (their ids become base + id), and its placement units are packed into our
    // node blocks in the order the part made them, children before parents, so each
    // LOD node learns its children's block and offset before it is placed itself.
    void merge(Emitter& part, std::vector<std::vector<std::uint8_t>>& triangle_blocks, Pending& root) {
        triangles.flush();
        const std::uint32_t tri_base = triangles.blocks();
        for (auto& b : triangle_blocks) adopt_triangle_block(std::move(b));
        triangle_blocks.clear();
        std::vector<std::pair<std::uint32_t, std::size_t>> placed(part.units.size());
        auto resolve = [&](Pending& t) {
            for (const Patch& q : t.patches) {
                std::uint8_t* at = t.bytes.data() + q.offset;
                std::uint32_t w;
                if (q.unit < 0) {
                    std::memcpy(&w, at, 4);
                    w += tri_base;
                    std::memcpy(at, &w, 4);
                    continue;
                }
                const auto [block, off] = placed[static_cast<std::size_t>(q.unit)];
                std::memcpy(&w, at, 4);
                w = (w & ~(8191u << 17)) | (static_cast<std::uint32_t>(off / 8) << 17);
                std::memcpy(at, &w, 4);
                std::memcpy(at + 12, &block, 4);
            }
            t.patches.clear();
        };
        for (std::size_t u = 0; u < part.units.size(); ++u) {
            Unit& unit = part.units[u];
            resolve(unit.data);
            placed[u] = place(unit.level, &unit.data, nullptr);
        }
        part.units.clear();
        resolve(root);
        const ModelWriterStats& s = part.stats;
        stats.basic_nodes += s.basic_nodes;
        stats.lod_nodes += s.lod_nodes;
        stats.leaves += s.leaves;
        stats.empty_children += s.empty_children;
        stats.voxels_one += s.voxels_one;
        stats.voxels_six += s.voxels_six;
        stats.references += s.references;
        stats.stored_triangles += s.stored_triangles;
        stats.stored_vertices += s.stored_vertices;
        for (std::size_t level = 0; level < s.level_nodes.size(); ++level) {
            ensure_level(level);
            stats.level_nodes[level] += s.level_nodes[level];
            stats.level_voxels[level] += s.level_voxels[level];
        }
    }
};

}  // namespace

struct ModelWriter::Impl {
    ModelWriterParams p;
    BlockSink sink;
    ProgressCounter counter;
    Emitter main;
    std::unordered_map<int, Pending> pending;
    int next_handle = 0;

    Impl(const ModelWriterParams& params, BlockSink s, ProgressSink pr)
        : p(params), sink(std::move(s)),
          main(p, counter, [this](int level, std::vector<std::uint8_t>&& bytes) {
              sink(level, bytes.data(), bytes.size());
          }) {
        counter.sink = std::move(pr);
    }

    int keep(Pending&& t) {
        const int h = next_handle++;
        pending.emplace(h, std::move(t));
        return h;
    }
    Pending take(int handle) {
        auto it = pending.find(handle);
        if (it == pending.end()) throw std::invalid_argument("unknown or already used treelet handle " + std::to_string(handle));
        Pending t = std::move(it->second);
        pending.erase(it);
        return t;
    }
};

ModelWriter::ModelWriter(const ModelWriterParams& params, BlockSink sink, ProgressSink progress)
    : impl_(std::make_unique<Impl>(params, std::move(sink), std::move(progress))), stats_(impl_->main.stats) {}

ModelWriter::~ModelWriter() = default;

int ModelWriter::add_subtree(const float* corners, const std::uint32_t* ids, const std::uint32_t* colours,
                             std::size_t n, const Box3f& cell, int level) {
    if (n == 0) throw std::invalid_argument("a subtree needs at least one triangle");
    if (impl_->p.has_colours && colours == nullptr) throw std::invalid_argument("the model has colours; pass them");
    const auto t0 = std::chrono::steady_clock::now();
    const auto* verts = reinterpret_cast<const Vec3f*>(corners);
    KdTree tree = build_kdtree(TriangleSoup{verts, n}, impl_->p.kd, &cell);
    const auto t1 = std::chrono::steady_clock::now();
    stats_.kd_build_ms += std::chrono::duration<double, std::milli>(t1 - t0).count();
    stats_.degenerate += tree.stats.degenerate;
    stats_.max_depth = std::max(stats_.max_depth, tree.stats.max_depth + 3 * level);
    if (tree.nodes.empty() || (tree.nodes[0].is_leaf() && tree.nodes[0].count() == 0)) {
        throw std::invalid_argument("no triangle of this subtree lies inside its cell");
    }
    Emitter& m = impl_->main;
    auto bind = [&](Emitter& e) {
        e.tree = &tree;
        e.corners = verts;
        e.ids = ids;
        e.colours = impl_->p.has_colours ? colours : nullptr;
    };
    bind(m);
    const auto lvl = static_cast<std::size_t>(level);

    // The subtrees below the root treelet's LOD nodes are independent: emit them in
    // parallel into buffered streams, then merge them in order, so the file does not
    // depend on the thread count.
    std::vector<LocalNode> top;
    m.collect_kd(0, cell, 0, top);
    struct Job {
        std::uint32_t node;
        Box3f cell;
    };
    std::vector<Job> jobs;
    for (const LocalNode& t : top) {
        if (t.kind != LocalNode::Lod) continue;
        if ((t.empty & kLeftEmpty) == 0) jobs.push_back({t.kd_left, child_cell(t.cell, t.axis, t.split, 0)});
        if ((t.empty & kRightEmpty) == 0) jobs.push_back({t.kd_right, child_cell(t.cell, t.axis, t.split, 1)});
    }
    Pending root;
    const unsigned lanes = impl_->p.kd.threads == 0 ? hardware_threads() : impl_->p.kd.threads;
    if (jobs.size() >= 2) {
        // Parts buffer only triangle blocks: their treelets go out as placement units.
        std::vector<std::vector<std::vector<std::uint8_t>>> buffers(jobs.size());
        std::vector<std::unique_ptr<Emitter>> parts;
        for (auto& buffer : buffers) {
            parts.push_back(std::make_unique<Emitter>(
                impl_->p, impl_->counter,
                [&buffer](int, std::vector<std::uint8_t>&& bytes) {
                    buffer.push_back(std::move(bytes));
                }));
            parts.back()->defer = true;
            bind(*parts.back());
        }
        std::vector<Pending> roots(jobs.size());
        ThreadPool::global().parallel_for(jobs.size(), [&](std::size_t i, unsigned) {
            Emitter& e = *parts[i];
            roots[i] = e.emit_kd_treelet(jobs[i].node, jobs[i].cell, lvl + 1);
            e.triangles.flush();
        }, lanes);
        for (std::size_t i = 0; i < jobs.size(); ++i) m.merge(*parts[i], buffers[i], roots[i]);
        root = m.emit_kd_treelet(0, cell, lvl, &roots);
    } else {
        root = m.emit_kd_treelet(0, cell, lvl);
    }
    m.tree = nullptr;
    stats_.emit_ms += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t1).count();
    return impl_->keep(std::move(root));
}

int ModelWriter::add_inner_treelet(int level, const Box3f& cell, const std::array<int, 7>& axes,
                                   const std::array<float, 7>& splits, const std::array<int, 8>& children) {
    // Presence bottom-up: a node exists when any child slot below it is filled.
    bool present[7] = {};
    for (int j = 0; j < 4; ++j) present[3 + j] = children[2 * j] >= 0 || children[2 * j + 1] >= 0;
    for (int i = 0; i < 2; ++i) present[1 + i] = present[3 + 2 * i] || present[4 + 2 * i];
    present[0] = present[1] || present[2];
    if (!present[0]) throw std::invalid_argument("an inner treelet needs at least one child");
    for (int h = 0; h < 7; ++h) {
        if (axes[static_cast<std::size_t>(h)] < 0 || axes[static_cast<std::size_t>(h)] > 2) throw std::invalid_argument("split axis must be 0, 1 or 2");
    }

    std::vector<LocalNode> nodes;
    auto collect = [&](auto&& self, int h, const Box3f& c, int depth) -> void {
        LocalNode n;
        n.cell = c;
        n.axis = axes[static_cast<std::size_t>(h)];
        n.split = splits[static_cast<std::size_t>(h)];
        if (depth == kTreeletHeight - 1) {
            const int j = h - 3;
            n.kind = LocalNode::Lod;
            n.child_handles[0] = children[static_cast<std::size_t>(2 * j)];
            n.child_handles[1] = children[static_cast<std::size_t>(2 * j + 1)];
            n.empty = (n.child_handles[0] < 0 ? kLeftEmpty : 0u) | (n.child_handles[1] < 0 ? kRightEmpty : 0u);
            nodes.push_back(n);
            return;
        }
        const int l = 2 * h + 1, r = 2 * h + 2;
        n.empty = (present[l] ? 0u : kLeftEmpty) | (present[r] ? 0u : kRightEmpty);
        const std::size_t at = nodes.size();
        nodes.push_back(n);
        if (present[l]) {
            nodes[at].left = static_cast<int>(nodes.size());
            self(self, l, child_cell(c, n.axis, n.split, 0), depth + 1);
        }
        if (present[r]) {
            nodes[at].right = static_cast<int>(nodes.size());
            self(self, r, child_cell(c, n.axis, n.split, 1), depth + 1);
        }
    };
    collect(collect, 0, cell, 0);

    Emitter& m = impl_->main;
    Pending self;
    for (LocalNode& n : nodes) {
        if (n.kind != LocalNode::Lod) continue;
        const bool has_l = n.child_handles[0] >= 0, has_r = n.child_handles[1] >= 0;
        Pending l, r;
        if (has_l) l = impl_->take(n.child_handles[0]);
        if (has_r) r = impl_->take(n.child_handles[1]);
        m.finish_lod(n, has_l ? &l : nullptr, has_r ? &r : nullptr, static_cast<std::size_t>(level), self);
    }
    m.serialise(nodes, static_cast<std::size_t>(level), self);
    return impl_->keep(std::move(self));
}

void ModelWriter::finish(int root) {
    Emitter& m = impl_->main;
    Pending r = impl_->take(root);
    if (!m.level_buf.empty() && !m.level_buf[0].empty()) throw std::logic_error("level 0 already written");
    m.place(0, &r, nullptr);
    for (std::size_t level = 0; level < m.level_buf.size(); ++level) m.flush_level(level);
    m.triangles.flush();
    if (!impl_->pending.empty()) throw std::logic_error("treelets left unplaced: the tree has more than one root");
    if (impl_->counter.sink) impl_->counter.sink(impl_->counter.references);
}

}  // namespace vastray
