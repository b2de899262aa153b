#include "writer/level_files.h"

#include <cerrno>
#include <cstring>
#include <stdexcept>

namespace vastray::writer {

LevelFiles::LevelFiles(const std::string& output, std::uint64_t start)
    : output_(output), model_(std::make_unique<DirectAppender>(output, start)), start_(start), end_(start) {}

LevelFiles::~LevelFiles() {
    for (auto& [level, f] : files_) std::fclose(f);
}

std::string LevelFiles::path(int level) const {
    if (!output_.empty()) return output_;
    return dir_ + "/" + (level < 0 ? std::string("triangles.blk") : "level" + std::to_string(level) + ".blk");
}

void LevelFiles::write(int level, std::uint32_t tier, const StoredBlock& block) {
    std::uint64_t at = 0;
    if (model_) {
        at = model_->position();
        model_->append(block.bytes.data(), block.bytes.size());
    } else {
        auto it = files_.find(level);
        if (it == files_.end()) {
            std::FILE* f = std::fopen(path(level).c_str(), "wb");
            if (f == nullptr) throw std::runtime_error(path(level) + ": cannot create: " + std::strerror(errno));
            std::setvbuf(f, nullptr, _IOFBF, 1 << 20);
            it = files_.emplace(level, f).first;
        }
        if (std::fwrite(block.bytes.data(), 1, block.bytes.size(), it->second) != block.bytes.size()) {
            throw std::runtime_error(path(level) + ": write failed: " + std::strerror(errno));
        }
        at = sizes_[level];
        sizes_[level] += block.bytes.size();
    }
    entries_[level].push_back({static_cast<std::uint32_t>(block.bytes.size()), block.raw_size, block.crc32, block.codec, tier});
    offsets_[level].push_back(at);
}

void LevelFiles::close() {
    std::string failure;
    for (auto& [level, f] : files_) {
        if (std::fflush(f) != 0 && failure.empty()) failure = path(level) + ": write failed: " + std::strerror(errno);
        std::fclose(f);
    }
    files_.clear();
    if (model_) {
        end_ = model_->position();
        try {
            model_->finish();
        } catch (const std::exception& e) {
            if (failure.empty()) failure = e.what();
        }
        direct_ = model_->direct();
        model_.reset();
    }
    if (!failure.empty()) throw std::runtime_error(failure);
}

}  // namespace vastray::writer
