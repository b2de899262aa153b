#include "vastray/model_index.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <stdexcept>

#include "vastray/crc32.h"
#include "vastray/format.h"
#include "vastray/lz4.h"

namespace vastray {

namespace {

using namespace format;

template <typename T>
T load(const std::uint8_t* p) {
    T v;
    std::memcpy(&v, p, sizeof v);
    return v;
}

bool read_exact(int fd, std::uint8_t* out, std::size_t size, std::uint64_t offset) {
    while (size > 0) {
        const ssize_t n = ::pread(fd, out, size, static_cast<off_t>(offset));
        if (n < 0 && errno == EINTR) continue;
        if (n <= 0) return false;
        out += n;
        size -= static_cast<std::size_t>(n);
        offset += static_cast<std::uint64_t>(n);
    }
    return true;
}

}  // namespace

ModelIndex::ModelIndex(const std::string& path) : path_(path) {
    auto fail = [&](const std::string& what) -> std::runtime_error {
        return std::runtime_error(path_ + ": " + what);
    };
    fd_ = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd_ < 0) throw fail(std::string("cannot open: ") + std::strerror(errno));
    try {
        struct stat st {};
        if (::fstat(fd_, &st) != 0) throw fail(std::string("cannot stat: ") + std::strerror(errno));
        const auto size = static_cast<std::uint64_t>(st.st_size);
        std::uint8_t h[kHeaderSize] = {};
        if (size < 8 || !read_exact(fd_, h, 8, 0) || std::memcmp(h, kMagic, 8) != 0) {
            throw fail("not a vastray model (bad magic bytes)");
        }
        if (size < kHeaderSize || !read_exact(fd_, h, kHeaderSize, 0)) {
            throw fail("truncated: shorter than the 256-byte header");
        }
        const auto version = load<std::uint32_t>(h + 8);
        if (version < kOldestVersion || version > kVersion) {
            throw fail("format version " + std::to_string(version) + " is not supported (this vastray reads versions " +
                       std::to_string(kOldestVersion) + " to " + std::to_string(kVersion) +
                       "); rebuild the model with this version");
        }
        std::uint8_t zeroed[kHeaderSize];
        std::memcpy(zeroed, h, kHeaderSize);
        std::memset(zeroed + kHeaderCrcAt, 0, 4);
        if (crc32(zeroed, kHeaderSize) != load<std::uint32_t>(h + kHeaderCrcAt)) {
            throw fail("header checksum mismatch (the header is corrupted)");
        }
        file_size_ = load<std::uint64_t>(h + 184);
        if (file_size_ != size) throw fail("file size differs from its header (truncated or appended to)");
        if (load<std::uint32_t>(h + 12) != kHeaderSize || load<std::uint32_t>(h + 20) != kBlockSize) {
            throw fail("unsupported block or header size");
        }
        if (load<std::uint32_t>(h + 24) != kCodecFamilyLz4) throw fail("unsupported block codec family");
        const auto flags = load<std::uint32_t>(h + 16);
        const std::uint32_t known = kFlagColours | kFlagTriangleIds | (version >= 2 ? kFlagPartIds : 0u) |
                                    (version >= 3 ? kFlagQuantizedSplits : 0u) | (version >= 4 ? kFlagQuantizedVertices : 0u) |
                                    (version >= 5 ? kFlagCompactTriangles | kFlagTiered : 0u) |
                                    (version >= 7 ? kFlagPackedTreelets : 0u) | (version >= 8 ? kFlagVoxelErrors : 0u);
        if (!(flags & kFlagTriangleIds) || (flags & ~known)) {
            throw fail("unsupported attribute flags");
        }
        // Coarseness tiers (version 5): streams per level; bytes 224-227 were padding before.
        tiered_ = (flags & kFlagTiered) != 0;
        const std::uint32_t tier_field = version >= 5 ? load<std::uint32_t>(h + kTierCountAt) : 0;
        if (!tiered_ && tier_field != 0) throw fail("tier count set without the tiered flag");
        if (tiered_ && (tier_field == 0 || tier_field > kMaxTiers)) throw fail("implausible tier count");
        tier_count_ = tiered_ ? tier_field : 1;
        // The parts section (version 2; docs/FORMAT.md §4a): the blocks end where it starts.
        std::uint64_t blocks_end = size;
        if (version >= 2) {
            const auto parts_offset = load<std::uint64_t>(h + kPartsOffsetAt);
            const auto parts_size = load<std::uint64_t>(h + kPartsSizeAt);
            const auto parts_crc = load<std::uint32_t>(h + kPartsCrcAt);
            part_count_ = load<std::uint32_t>(h + kPartCountAt);
            if (!(flags & kFlagPartIds)) {
                if (parts_offset || parts_size || parts_crc || part_count_) throw fail("parts fields set without the part-ids flag");
            } else {
                if (part_count_ == 0 || parts_size < kPartsHead || parts_offset > size || parts_size != size - parts_offset) {
                    throw fail("parts section does not fit the file");
                }
                std::vector<std::uint8_t> section(parts_size);
                if (!read_exact(fd_, section.data(), section.size(), parts_offset)) throw fail("cannot read the parts section");
                if (crc32(section.data(), section.size()) != parts_crc) throw fail("parts section damaged (checksum mismatch)");
                blocks_end = parts_offset;
            }
        }
        has_colours_ = (flags & kFlagColours) != 0;
        quantized_splits_ = (flags & kFlagQuantizedSplits) != 0;
        packed_treelets_ = (flags & kFlagPackedTreelets) != 0;
        if (packed_treelets_ && !quantized_splits_) throw fail("packed treelets flag set without quantized splits");
        voxel_errors_ = (flags & kFlagVoxelErrors) != 0;
        if (voxel_errors_ && !quantized_splits_) throw fail("voxel errors flag set without quantized splits");
        const auto level_count = load<std::uint32_t>(h + 28);
        for (int a = 0; a < 3; ++a) {
            centre_[a] = load<double>(h + 32 + 8 * a);
            root_cell_.lo[a] = load<float>(h + 56 + 4 * a);
            root_cell_.hi[a] = load<float>(h + 68 + 4 * a);
        }
        quantized_vertices_ = (flags & kFlagQuantizedVertices) != 0;
        compact_triangles_ = (flags & kFlagCompactTriangles) != 0;
        vertex_steps_ = vertex_grid_steps(root_cell_.lo, root_cell_.hi);
        triangle_count_ = load<std::uint64_t>(h + 80);
        input_triangles_ = load<std::uint64_t>(h + 88);
        const auto block_count = load<std::uint64_t>(h + 152);
        const auto index_offset = load<std::uint64_t>(h + 160);
        const auto data_offset = load<std::uint64_t>(h + 168);
        if (level_count < 2 || block_count == 0 || block_count > (1ull << 32)) throw fail("implausible level or block count");
        const std::uint64_t streams = std::uint64_t{level_count} * tier_count_;
        const std::uint64_t index_size = kLevelRecord * streams + kEntryRecord * block_count;
        if (index_offset + index_size != data_offset || data_offset > blocks_end) throw fail("index does not fit the file");
        std::vector<std::uint8_t> index(index_size);
        if (!read_exact(fd_, index.data(), index.size(), index_offset)) throw fail("cannot read the block index");
        if (crc32(index.data(), index.size()) != load<std::uint32_t>(h + 192)) {
            throw fail("block index checksum mismatch (the index is corrupted)");
        }
        // Streams tile the index in order. Untiered, every level has blocks; tiered, a
        // stream may be empty, but each level has blocks and the root's stream begins it.
        std::uint64_t expected = 0;
        for (std::uint64_t r = 0; r < streams; ++r) {
            const auto first = load<std::uint32_t>(index.data() + kLevelRecord * r);
            const auto count = load<std::uint32_t>(index.data() + kLevelRecord * r + 4);
            if (first != expected || (count == 0 && !tiered_)) throw fail("levels do not tile the block index");
            if (r % tier_count_ == 0) level_first_.push_back(first);
            stream_first_.push_back(first);
            expected += count;
        }
        if (expected != block_count) throw fail("levels do not cover every block");
        level_first_.push_back(static_cast<std::uint32_t>(expected));
        stream_first_.push_back(static_cast<std::uint32_t>(expected));
        for (std::size_t l = 0; l < level_count; ++l) {
            if (level_first_[l] == level_first_[l + 1]) throw fail("levels do not tile the block index");
        }
        if (stream_first_[1] == 0) throw fail("levels do not tile the block index");
        entries_.resize(block_count);
        const std::uint8_t* e = index.data() + kLevelRecord * streams;
        for (std::size_t i = 0; i < block_count; ++i, e += kEntryRecord) {
            BlockEntry& b = entries_[i];
            b.offset = load<std::uint64_t>(e);
            b.stored_size = load<std::uint32_t>(e + 8);
            b.raw_size = load<std::uint32_t>(e + 12);
            b.crc32 = load<std::uint32_t>(e + 16);
            b.codec = load<std::uint32_t>(e + 20);
            if (b.offset < data_offset || b.offset + b.stored_size > blocks_end || b.raw_size > kBlockSize ||
                b.stored_size > kBlockSize + kBlockSize / 255 + 16) {
                throw fail("block " + std::to_string(i) + " lies outside the file or is oversized");
            }
        }
    } catch (...) {
        ::close(fd_);
        throw;
    }
}

ModelIndex::~ModelIndex() {
    if (fd_ >= 0) ::close(fd_);
}

std::size_t ModelIndex::level_of(std::size_t block) const {
    const auto it = std::upper_bound(level_first_.begin(), level_first_.end() - 1, static_cast<std::uint32_t>(block));
    return static_cast<std::size_t>(it - level_first_.begin()) - 1;
}

std::string ModelIndex::level_name(std::size_t block) const {
    // The numbering `vastray inspect` prints: LOD levels 0.., then the triangle level.
    const std::size_t level = level_of(block);
    if (level + 1 == level_count()) return "triangle level";
    return "LOD level " + std::to_string(level);
}

void ModelIndex::read_ahead(std::size_t first, std::size_t last) const {
    if (first > last || last >= entries_.size()) return;
    // One call per run of blocks that follow one another in the file too: consecutive
    // ids need not be neighbours there (FORMAT.md §3), and advice spanning the blocks
    // between them would read what no one asked for.
    std::size_t run = first;
    for (std::size_t i = first + 1; i <= last + 1; ++i) {
        if (i <= last && entries_[i].offset == entries_[i - 1].offset + entries_[i - 1].stored_size) continue;
        const BlockEntry& a = entries_[run];
        const BlockEntry& b = entries_[i - 1];
        posix_fadvise(fd_, static_cast<off_t>(a.offset), static_cast<off_t>(b.offset + b.stored_size - a.offset),
                      POSIX_FADV_WILLNEED);
        run = i;
    }
}

std::string ModelIndex::read_block(std::size_t block, std::uint8_t* out, std::vector<std::uint8_t>& scratch) const {
    const BlockEntry& e = entries_[block];
    // Only failures pay for naming the block.
    auto fail = [&](const std::string& what) {
        return "block " + std::to_string(block) + " (" + level_name(block) + "): " + what;
    };
    if (e.codec != kCodecStored && e.codec != kCodecLz4) return fail("unknown codec " + std::to_string(e.codec));
    if (e.codec == kCodecStored && e.stored_size != e.raw_size) return fail("stored block size differs from its raw size");
    // A stored block is read straight into its destination; a compressed one via scratch.
    std::uint8_t* stored = out;
    if (e.codec == kCodecLz4) {
        scratch.resize(e.stored_size);
        stored = scratch.data();
    }
    if (!read_exact(fd_, stored, e.stored_size, e.offset)) {
        const int error = errno ? errno : EIO;
        return fail(std::string("read failed: ") + std::strerror(error));
    }
    if (crc32(stored, e.stored_size) != e.crc32) return fail("checksum mismatch (the block is corrupted)");
    if (e.codec == kCodecStored) return {};
    const Lz4Status status = lz4_decompress_block(stored, e.stored_size, out, e.raw_size);
    if (status != Lz4Status::Ok) return fail(std::string("LZ4 data is corrupted (") + lz4_status_message(status) + ")");
    return {};
}

}  // namespace vastray
