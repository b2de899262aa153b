#include "writer/node_blocks.h"

namespace vastray::writer {

void NodeBlocks::ensure(std::size_t level) {
    if (open_.size() > level) return;
    open_.resize(level + 1);
    ensure_level(stats_, level);
}

bool NodeBlocks::started(std::size_t level) const {
    return level < open_.size() && (!open_[level].empty() || stats_.level_blocks[level] > 0);
}

void NodeBlocks::flush(std::size_t level) {
    if (level >= open_.size()) return;
    auto& buf = open_[level];
    if (buf.empty()) return;
    stats_.level_blocks[level]++;
    stats_.level_bytes[level] += buf.size();
    out_(static_cast<int>(level), store_block(buf));
    buf.clear();
}

void NodeBlocks::flush_all() {
    for (std::size_t level = 0; level < open_.size(); ++level) flush(level);
}

std::pair<std::uint32_t, std::size_t> NodeBlocks::place(std::size_t level, const Pending* a, const Pending* b) {
    ensure(level);
    auto& buf = open_[level];
    const std::size_t need = (a ? a->bytes.size() : 0) + (b ? b->bytes.size() : 0);
    if (buf.size() + need > format::kBlockSize) flush(level);
    const std::size_t off = buf.size();
    for (const Pending* t : {a, b}) {
        if (t != nullptr) buf.insert(buf.end(), t->bytes.begin(), t->bytes.end());
    }
    stats_.treelets += (a ? 1 : 0) + (b ? 1 : 0);
    return {static_cast<std::uint32_t>(stats_.level_blocks[level]), off};
}

}  // namespace vastray::writer
