#include "writer/level_files.h"

#include <cerrno>
#include <cstring>
#include <stdexcept>

namespace vastray::writer {

LevelFiles::LevelFiles(std::string dir, const std::string& output, std::uint64_t start)
    : dir_(std::move(dir)), output_(output), triangles_(std::make_unique<DirectAppender>(output, start)),
      triangles_start_(start), triangles_end_(start) {}

LevelFiles::~LevelFiles() {
    for (auto& [level, f] : files_) std::fclose(f);
}

std::string LevelFiles::path(int level) const {
    if (level < 0 && !output_.empty()) return output_;
    return dir_ + "/" + (level < 0 ? std::string("triangles.blk") : "level" + std::to_string(level) + ".blk");
}

void LevelFiles::write(int level, std::uint32_t tier, const StoredBlock& block) {
    if (level < 0 && triangles_) {
        triangles_->append(block.bytes.data(), block.bytes.size());
        entries_[level].push_back({static_cast<std::uint32_t>(block.bytes.size()), block.raw_size, block.crc32, block.codec, tier});
        return;
    }
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
    entries_[level].push_back({static_cast<std::uint32_t>(block.bytes.size()), block.raw_size, block.crc32, block.codec, tier});
}

void LevelFiles::close() {
    std::string failure;
    for (auto& [level, f] : files_) {
        if (std::fflush(f) != 0 && failure.empty()) failure = path(level) + ": write failed: " + std::strerror(errno);
        std::fclose(f);
    }
    files_.clear();
    if (triangles_) {
        triangles_end_ = triangles_->position();
        try {
            triangles_->finish();
        } catch (const std::exception& e) {
            if (failure.empty()) failure = e.what();
        }
        triangles_direct_ = triangles_->direct();
        triangles_.reset();
    }
    if (!failure.empty()) throw std::runtime_error(failure);
}

}  // namespace vastray::writer
