#include "writer/node_blocks.h"

namespace vastray::writer {

std::vector<std::uint8_t>& NodeBlocks::open(std::size_t level, std::uint32_t tier) {
    if (open_.size() <= level) open_.resize(level + 1);
    if (open_[level].size() <= tier) open_[level].resize(tier + 1);
    node_stream(stats_, level, tier);
    return open_[level][tier];
}

bool NodeBlocks::started(std::size_t level) const {
    if (level < open_.size()) {
        for (const auto& buf : open_[level]) {
            if (!buf.empty()) return true;
        }
    }
    if (level < stats_.node_streams.size()) {
        for (const StreamStats& s : stats_.node_streams[level]) {
            if (s.blocks > 0) return true;
        }
    }
    return false;
}

void NodeBlocks::flush(std::size_t level, std::uint32_t tier) {
    if (level >= open_.size() || tier >= open_[level].size()) return;
    auto& buf = open_[level][tier];
    if (buf.empty()) return;
    StreamStats& s = node_stream(stats_, level, tier);
    s.blocks++;
    s.bytes += buf.size();
    out_(static_cast<int>(level), tier, buf);
    buf.clear();
}

void NodeBlocks::flush_all() {
    for (std::size_t level = 0; level < open_.size(); ++level) {
        for (std::size_t tier = 0; tier < open_[level].size(); ++tier) flush(level, static_cast<std::uint32_t>(tier));
    }
}

std::pair<std::uint32_t, std::size_t> NodeBlocks::place(std::size_t level, std::uint32_t tier, const Pending* a,
                                                        const Pending* b) {
    auto& buf = open(level, tier);
    const std::size_t need = (a ? a->bytes.size() : 0) + (b ? b->bytes.size() : 0);
    if (buf.size() + need > format::kBlockSize) flush(level, tier);
    const std::size_t off = buf.size();
    StreamStats& s = node_stream(stats_, level, tier);
    for (const Pending* t : {a, b}) {
        if (t == nullptr) continue;
        buf.insert(buf.end(), t->bytes.begin(), t->bytes.end());
        s.items += t->nodes;
        s.extra += t->voxels;
        stats_.treelets++;
    }
    return {static_cast<std::uint32_t>(s.blocks), off};
}

}  // namespace vastray::writer
