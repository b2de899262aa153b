#include "writer/model_blocks.h"

namespace vastray::writer {

ModelBlocks::ModelBlocks(const std::string& output, std::uint64_t start)
    : output_(output), file_(std::make_unique<DirectAppender>(output, start)), start_(start), end_(start) {}

void ModelBlocks::write(int level, std::uint32_t tier, const StoredBlock& block) {
    offsets_[level].push_back(file_->position());
    file_->append(block.bytes.data(), block.bytes.size());
    entries_[level].push_back({static_cast<std::uint32_t>(block.bytes.size()), block.raw_size, block.crc32, block.codec, tier});
}

void ModelBlocks::close() {
    if (!file_) return;
    end_ = file_->position();
    std::unique_ptr<DirectAppender> file = std::move(file_);
    file->finish();
    direct_ = file->direct();
}

}  // namespace vastray::writer
