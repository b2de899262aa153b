#include "writer/subtree_emitter.h"

#include <algorithm>
#include <cstring>
#include <stdexcept>
#include <utility>

#include "writer/voxel_sampling.h"

namespace vastray::writer {

using namespace format;

void ProgressCounter::add(std::uint64_t n) {
    std::lock_guard<std::mutex> lock(mutex);
    references += n;
    if (sink && references - reported >= (1u << 16)) {
        reported = references;
        sink(references);
    }
}

SubtreeEmitter::SubtreeEmitter(const ModelWriterParams& params, ProgressCounter& counter, BlockStream out, bool defer)
    : p_(params), counter_(counter), out_(std::move(out)),
      pack_([this](int level, std::uint32_t tier, const std::vector<std::uint8_t>& raw) {
          out_(level, tier, store_block(raw, p_.lz4_hc_level));
      }),
      defer_(defer), tiering_(params.root_radius, params.tier_width, params.tier_coarse_octaves), nodes(pack_, stats),
      triangles(params.has_colours, params.quantized_vertices ? &params.vertex_steps : nullptr, params.compact_triangles,
                pack_, stats) {}

std::uint32_t SubtreeEmitter::reference(std::uint32_t tier, std::uint32_t block) const {
    if (!tiering_.enabled()) return block;
    if (block >= kMaxStreamBlocks) throw std::length_error("a tier of a level holds more blocks than the format can number");
    return block_ref(tier, block);
}

void SubtreeEmitter::code_error(TreeletNode& lod) const {
    if (!voxel_errors()) return;
    const float radius = format::cell_radius(lod.cell.extent());
    const float floor = radius * std::clamp(p_.voxel_error_floor, 0.0f, 1.0f);
    lod.error_code = format::lod_error_code_for(radius, std::max(std::min(lod.error, radius), floor));
}

float SubtreeEmitter::lod_key(const TreeletNode& lod) const {
    const float radius = format::cell_radius(lod.cell.extent());
    return voxel_errors() ? format::lod_error(radius, lod.error_code) : radius;
}

void SubtreeEmitter::finish_lod(TreeletNode& node, Pending* a, Pending* b, std::size_t level, Pending& self) {
    const FaceSamples s = sample_voxel(node.cell, a ? &a->proxies : nullptr, b ? &b->proxies : nullptr,
                                       p_.voxel_rays_per_axis);
    const QuantisedVoxel q = quantise_voxel(s, p_.one_sample_colour, p_.one_sample_normal, p_.packed_voxels);
    std::copy(q.words, q.words + q.count, node.voxel);
    node.voxel_words = q.count;
    (q.count == 1 ? stats.voxels_one : stats.voxels_six)++;
    stats.voxels_packed += q.count == 4 ? 1 : 0;
    self.proxies.push_back({node.cell, q.seen});
    if (voxel_errors()) {
        stats.lod_errors_below_radius += node.error_code < format::kErrorCodeMax ? 1 : 0;
        stats.lod_error_ratio_sum += static_cast<double>(node.error_code + 1) / 256.0;
    }
    const std::uint32_t tier = tier_below(node);
    if (defer_) {
        Unit u{level + 1, tier, {}};
        // One allocation each (this runs for every LOD node of a job).
        u.data.bytes.reserve((a ? a->bytes.size() : 0) + (b ? b->bytes.size() : 0));
        u.data.patches.reserve((a ? a->patches.size() : 0) + (b ? b->patches.size() : 0));
        for (const Pending* t : {a, b}) {
            if (t == nullptr) continue;
            for (const Patch& patch : t->patches) {
                u.data.patches.push_back({static_cast<std::uint32_t>(u.data.bytes.size()) + patch.offset, patch.unit});
            }
            u.data.bytes.insert(u.data.bytes.end(), t->bytes.begin(), t->bytes.end());
            u.data.nodes += t->nodes;
            u.data.voxels += t->voxels;
        }
        node.unit = static_cast<int>(units_.size());
        units_.push_back(std::move(u));
    } else {
        const auto [block, off] = nodes.place(level + 1, tier, a, b);
        node.child_block = reference(tier, block);
        node.child_off = static_cast<std::uint32_t>(off);
    }
    node.right_from_left = a != nullptr && b != nullptr ? static_cast<std::uint32_t>(a->bytes.size()) : 0;
    const Vec3f e = node.cell.extent();
    node.radius = format::cell_radius(e);
}

Pending SubtreeEmitter::emit_kd_treelet(std::uint32_t root, const Box3f& cell, std::size_t level, std::uint32_t tier,
                                        const JobLookup* jobs) {
    // The treelet lists of the levels on the current path, kept between calls: a part
    // emits millions of treelets, and their allocations showed in the profile.
    if (depth_ == treelets_.size()) treelets_.emplace_back().reserve(7);
    std::vector<TreeletNode>& treelet = treelets_[depth_];
    treelet.clear();
    collect_kd_treelet(*tree_, root, cell, treelet);
    if (errors_ != nullptr) {
        for (TreeletNode& n : treelet) {
            n.error = errors_[n.kd_node];
            if (n.kind == TreeletNode::Lod) code_error(n);
        }
    }
    Pending self;
    std::size_t proxies = 0;  // one per LOD node and leaf; as many patches at most
    for (const TreeletNode& n : treelet) proxies += n.kind == TreeletNode::Basic ? 0 : 1;
    self.proxies.reserve(proxies);
    self.patches.reserve(proxies);
    struct Depth {
        std::size_t& d;
        explicit Depth(std::size_t& depth) : d(depth) { ++d; }
        ~Depth() { --d; }
    } nested(depth_);
    auto child = [&](std::uint32_t kd_node, const Box3f& child_cell, std::uint32_t child_tier) {
        Pending t;
        if (jobs == nullptr || !(*jobs)(kd_node, t)) t = emit_kd_treelet(kd_node, child_cell, level + 1, child_tier, jobs);
        return t;
    };
    for (TreeletNode& n : treelet) {
        if (n.kind == TreeletNode::Lod) {
            const bool has_l = (n.empty & kLeftEmpty) == 0, has_r = (n.empty & kRightEmpty) == 0;
            const std::uint32_t below = tier_below(n);
            Pending l, r;
            if (has_l) l = child(n.kd_left, child_cell(n.cell, n.axis, n.split, 0), below);
            if (has_r) r = child(n.kd_right, child_cell(n.cell, n.axis, n.split, 1), below);
            finish_lod(n, has_l ? &l : nullptr, has_r ? &r : nullptr, level, self);
        } else if (n.kind == TreeletNode::Leaf) {
            const KdNode& k = tree_->nodes[n.kd_node];
            const std::uint32_t* tris = tree_->tri_ids.data() + k.first();
            n.count = k.count();
            if (n.count > kMaxLeafTriangles) throw std::length_error("kd-tree leaf too large for the format");
            const auto [block, first] = triangles[tier].add_leaf(tris, n.count, src_);
            n.tri_block = reference(tier, block);
            n.first = first;
            self.proxies.push_back(leaf_proxy(src_, tris, n.count, n.cell));
            stats.references += n.count;
            // Progress goes to the shared (locked) counter in batches, not once per leaf.
            unreported_ += n.count;
            if (unreported_ >= kProgressBatch) {
                counter_.add(unreported_);
                unreported_ = 0;
            }
        }
    }
    serialise(treelet, self);
    if (depth_ == 1 && unreported_ > 0) {  // the outermost treelet: all of it is counted
        counter_.add(unreported_);
        unreported_ = 0;
    }
    return self;
}

void SubtreeEmitter::finish_deferred() {
    const std::uint32_t tiers = triangles.size();
    closed_.assign(tiers, 0);
    open_leaves_.assign(tiers, {});
    for (std::uint32_t k = 0; k < tiers; ++k) {
        TriangleBlocks* t = triangles.find(k);
        if (t == nullptr) continue;
        t->take_open_leaves(open_leaves_[k]);
        closed_[k] = t->blocks();
    }
    triangles.release();
}

void SubtreeEmitter::merge(SubtreeEmitter& part, std::vector<BufferedBlock>& triangle_blocks, Pending& root) {
    const bool tiered = tiering_.enabled();
    const auto tiers = static_cast<std::uint32_t>(part.closed_.size());
    // Per tier: the part's closed blocks follow ours, after our open one is closed.
    std::vector<std::uint32_t> base(tiers, 0);
    for (std::uint32_t k = 0; k < tiers; ++k) {
        if (part.closed_[k] == 0) continue;
        TriangleBlocks& t = triangles[k];
        t.flush();
        base[k] = t.blocks();
    }
    for (BufferedBlock& b : triangle_blocks) {
        triangles[b.tier].skip_block();
        out_(-1, b.tier, std::move(b.block));
    }
    triangle_blocks.clear();
    // The leaves of its open blocks join ours, in the order it added them.
    std::vector<std::vector<std::pair<std::uint32_t, std::uint32_t>>> moved(tiers);
    for (std::uint32_t k = 0; k < tiers; ++k) {
        for (const OpenLeaf& leaf : part.open_leaves_[k]) moved[k].push_back(triangles[k].add_leaf(leaf.tris, leaf.count, src_));
    }
    struct Placed {
        std::uint32_t reference;
        std::size_t offset;
    };
    std::vector<Placed> placed(part.units_.size());
    auto resolve = [&](Pending& t) {
        for (const Patch& q : t.patches) {
            std::uint8_t* at = t.bytes.data() + q.offset;
            std::uint32_t w;
            std::memcpy(&w, at, 4);
            if (q.unit < 0) {
                const std::uint32_t k = ref_tier(w, tiered), rel = ref_relative(w, tiered);
                if (k >= tiers) throw std::logic_error("a leaf refers to a tier its part never used");
                const std::vector<OpenLeaf>& open = part.open_leaves_[k];
                std::uint32_t w0;
                std::memcpy(&w0, at - 4, 4);
                if (rel == part.closed_[k] && !open.empty() && leaf_count(w0) > 0) {
                    // A leaf of the part's open block: where the merge put it. Leaves in a
                    // block have distinct first entries, added in rising order. (A leaf of
                    // no triangles reads no block: readers ignore its reference.)
                    const auto it = std::lower_bound(open.begin(), open.end(), leaf_first(w0),
                                                     [](const OpenLeaf& l, std::uint32_t f) { return l.first < f; });
                    if (it == open.end() || it->first != leaf_first(w0)) throw std::logic_error("an open leaf was lost in the merge");
                    const auto [block, first] = moved[k][static_cast<std::size_t>(it - open.begin())];
                    w0 = (w0 & ~0xffffu) | first;
                    std::memcpy(at - 4, &w0, 4);
                    w = reference(k, block);
                } else {
                    w = reference(k, base[k] + rel);
                }
                std::memcpy(at, &w, 4);
                continue;
            }
            const Placed& p = placed[static_cast<std::size_t>(q.unit)];
            w = format::with_child_offset(w, p.offset, packed_treelets());
            std::memcpy(at, &w, 4);
            std::memcpy(at + format::lod_child_block_at(p_.kd.quantized_splits), &p.reference, 4);
        }
        t.patches.clear();
    };
    for (std::size_t u = 0; u < part.units_.size(); ++u) {
        Unit& unit = part.units_[u];
        resolve(unit.data);
        const auto [block, off] = nodes.place(unit.level, unit.tier, &unit.data, nullptr);
        placed[u] = {reference(unit.tier, block), off};
    }
    part.units_.clear();
    resolve(root);
    const ModelWriterStats& s = part.stats;
    stats.basic_nodes += s.basic_nodes;
    stats.lod_nodes += s.lod_nodes;
    stats.leaves += s.leaves;
    stats.empty_children += s.empty_children;
    stats.voxels_one += s.voxels_one;
    stats.voxels_six += s.voxels_six;
    stats.voxels_packed += s.voxels_packed;
    stats.lod_errors_below_radius += s.lod_errors_below_radius;
    stats.lod_error_ratio_sum += s.lod_error_ratio_sum;
    stats.references += s.references;
    stats.stored_triangles += s.stored_triangles;
    stats.stored_vertices += s.stored_vertices;
    stats.vertex_bytes += s.vertex_bytes;
    stats.triangle_blocks += s.triangle_blocks;
    stats.triangle_bytes += s.triangle_bytes;
    for (std::uint32_t k = 0; k < s.triangle_streams.size(); ++k) triangle_stream(stats, k) += s.triangle_streams[k];
}

}  // namespace vastray::writer
