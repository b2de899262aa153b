// The writer's public face (vastray/model_writer.h): builds each in-core part's kd-tree,
// hands it to the emitters, and keeps finished treelets pending until the out-of-core
// treelets above them are added. The pieces live in native/src/writer/:
//   treelet          the in-memory treelet, collected from a kd-tree and serialised
//   voxel_sampling   leaf proxies, voxel samples and their quantisation
//   node_blocks      packing treelets into the blocks of their LOD level
//   triangle_blocks  packing leaf triangles into triangle blocks
//   subtree_emitter  emitting a kd-subtree; parallel parts merged in tree order
//   parallel_emission  cutting a part into jobs for all lanes, merging them as they finish
//   model_blocks     the model file the blocks are appended to, and their index entries
#include "vastray/model_writer.h"

#include <chrono>
#include <limits>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <utility>

#include "vastray/crc32.h"
#include "vastray/lz4.h"
#include "vastray/thread_pool.h"
#include "writer/parallel_emission.h"
#include "writer/subtree_emitter.h"
#include "writer/voxel_errors.h"

namespace vastray {

using namespace format;
using writer::Pending;
using writer::SubtreeEmitter;
using writer::TreeletNode;

StoredBlock store_block(const std::vector<std::uint8_t>& raw, int hc_level) {
    StoredBlock b;
    b.raw_size = static_cast<std::uint32_t>(raw.size());
    b.bytes.resize(lz4_compress_bound(raw.size()));
    const std::size_t n = lz4_compress_block(raw.data(), raw.size(), b.bytes.data(), b.bytes.size(), hc_level);
    if (n < raw.size()) {
        b.bytes.resize(n);
        b.codec = kCodecLz4;
    } else {
        b.bytes = raw;  // LZ4 would not shrink it: stored as it is
        b.codec = kCodecStored;
    }
    b.crc32 = crc32(b.bytes.data(), b.bytes.size());
    return b;
}

struct ModelWriter::Impl {
    ModelWriterParams p;
    BlockSink sink;
    writer::ProgressCounter counter;
    SubtreeEmitter main;
    std::unordered_map<int, Pending> pending;
    int next_handle = 0;

    Impl(const ModelWriterParams& params, BlockSink s, ProgressSink pr)
        : p(params), sink(std::move(s)),
          main(p, counter,
               [this](int level, std::uint32_t tier, StoredBlock&& block) { sink(level, tier, std::move(block)); },
               false) {
        counter.sink = std::move(pr);
        p.kd.huge_pages = false;  // a part's tree is written out and freed (kdtree.h)
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

int ModelWriter::add_subtree(const std::uint8_t* records, std::size_t stride, std::size_t n, const Box3f& cell, int level,
                             const Box3f* lod_parent) {
    if (n == 0) throw std::invalid_argument("a subtree needs at least one triangle");
    if (stride != record_size(impl_->p.has_colours)) throw std::invalid_argument("records of the wrong size for this model");
    const auto t0 = std::chrono::steady_clock::now();
    const TriangleSoup soup{reinterpret_cast<const Vec3f*>(records), n, stride / 4};
    KdTree tree = build_kdtree(soup, impl_->p.kd, &cell);
    const auto t1 = std::chrono::steady_clock::now();
    stats_.kd_build_ms += std::chrono::duration<double, std::milli>(t1 - t0).count();
    stats_.degenerate += tree.stats.degenerate;
    stats_.max_depth = std::max(stats_.max_depth, tree.stats.max_depth + 3 * level);
    if (tree.nodes.empty() || (tree.nodes[0].is_leaf() && tree.nodes[0].count() == 0)) {
        throw std::invalid_argument("no triangle of this subtree lies inside its cell");
    }
    const unsigned lanes = impl_->p.kd.threads == 0 ? hardware_threads() : impl_->p.kd.threads;
    std::vector<writer::Facet> facets(n);
    constexpr std::size_t kFacetChunk = 1 << 16;
    ThreadPool::global().parallel_for((n + kFacetChunk - 1) / kFacetChunk, [&](std::size_t c, unsigned) {
        const std::size_t end = std::min(n, (c + 1) * kFacetChunk);
        for (std::size_t i = c * kFacetChunk; i < end; ++i) facets[i] = writer::facet_of(&soup.v(i, 0));
    }, lanes);
    const writer::TriangleSource src{records, stride, impl_->p.has_colours, facets.data()};
    SubtreeEmitter& m = impl_->main;
    std::vector<float> errors;
    if (m.voxel_errors()) {
        const auto e0 = std::chrono::steady_clock::now();
        errors = writer::kd_errors(tree, src, cell, impl_->p.voxel_error_floor, lanes);
        stats_.voxel_error_ms += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - e0).count();
    }
    m.bind(&tree, src, errors.empty() ? nullptr : errors.data());
    const auto lvl = static_cast<std::size_t>(level);

    const std::uint32_t tier = lod_parent != nullptr ? m.tier_below(*lod_parent) : 0;
    Pending root = writer::emit_part(m, tree, src, cell, lvl, tier, impl_->p, impl_->counter, lanes);
    m.bind(nullptr, {});
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

    std::vector<TreeletNode> nodes;
    auto collect = [&](auto&& self, int h, const Box3f& c, int depth) -> void {
        TreeletNode n;
        n.cell = c;
        n.axis = axes[static_cast<std::size_t>(h)];
        n.split = splits[static_cast<std::size_t>(h)];
        if (depth == kTreeletHeight - 1) {
            const int j = h - 3;
            n.kind = TreeletNode::Lod;
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
            self(self, l, writer::child_cell(c, n.axis, n.split, 0), depth + 1);
        }
        if (present[r]) {
            nodes[at].right = static_cast<int>(nodes.size());
            self(self, r, writer::child_cell(c, n.axis, n.split, 1), depth + 1);
        }
    };
    collect(collect, 0, cell, 0);

    SubtreeEmitter& m = impl_->main;
    Pending self;
    constexpr float kNone = std::numeric_limits<float>::infinity();
    for (TreeletNode& n : nodes) {
        if (n.kind != TreeletNode::Lod) continue;
        const bool has_l = n.child_handles[0] >= 0, has_r = n.child_handles[1] >= 0;
        Pending l, r;
        if (has_l) l = impl_->take(n.child_handles[0]);
        if (has_r) r = impl_->take(n.child_handles[1]);
        // Surface errors (when kept) come up from the parts below, as in kd_errors.
        n.error = writer::inner_error(n.cell, n.axis, n.split, has_l ? l.error : kNone, has_r ? r.error : kNone);
        m.code_error(n);
        m.finish_lod(n, has_l ? &l : nullptr, has_r ? &r : nullptr, static_cast<std::size_t>(level), self);
    }
    for (auto it = nodes.rbegin(); it != nodes.rend(); ++it) {  // children before parents
        if (it->kind != TreeletNode::Basic) continue;
        const float l = it->left >= 0 ? nodes[static_cast<std::size_t>(it->left)].error : kNone;
        const float r = it->right >= 0 ? nodes[static_cast<std::size_t>(it->right)].error : kNone;
        it->error = writer::inner_error(it->cell, it->axis, it->split, l, r);
    }
    m.serialise(nodes, self);
    return impl_->keep(std::move(self));
}

void ModelWriter::finish(int root) {
    SubtreeEmitter& m = impl_->main;
    Pending r = impl_->take(root);
    if (m.nodes.started(0)) throw std::logic_error("level 0 already written");
    m.nodes.place(0, 0, &r, nullptr);
    m.nodes.flush_all();
    m.triangles.flush();
    if (!impl_->pending.empty()) throw std::logic_error("treelets left unplaced: the tree has more than one root");
    if (impl_->counter.sink) impl_->counter.sink(impl_->counter.references);
}

}  // namespace vastray
