// The CRC-32 and LZ4 block decoder vastray used before it linked libdeflate and liblz4,
// kept here as the baseline of bench/decode.py (they were written against the zlib CRC
// definition and the public LZ4 block format description).
#include "handwritten_codec.h"

#include <array>
#include <cstring>

namespace handwritten {

const char* lz4_status_message(Lz4Status status) {
    switch (status) {
        case Lz4Status::Ok: return "ok";
        case Lz4Status::Truncated: return "compressed data ends inside a sequence";
        case Lz4Status::BadOffset: return "match offset points before the start of the output";
        case Lz4Status::OutputOverflow: return "decoded data would exceed the expected size";
        case Lz4Status::SizeMismatch: return "decoded size differs from the expected size";
    }
    return "unknown error";
}

namespace {

// Lengths of 15 continue in following bytes, each adding up to 255.
bool read_length(const std::uint8_t*& in, const std::uint8_t* end, std::size_t& length) {
    for (;;) {
        if (in >= end) return false;
        const std::uint8_t b = *in++;
        length += b;
        if (b != 255) return true;
    }
}

}  // namespace

Lz4Status lz4_decompress_block(const std::uint8_t* src, std::size_t src_size, std::uint8_t* dst,
                               std::size_t dst_size) {
    const std::uint8_t* in = src;
    const std::uint8_t* const in_end = src + src_size;
    std::size_t out = 0;
    if (src_size == 0) return dst_size == 0 ? Lz4Status::Ok : Lz4Status::Truncated;
    for (;;) {
        if (in >= in_end) return Lz4Status::Truncated;
        const std::uint8_t token = *in++;
        std::size_t literals = token >> 4;
        if (literals == 15 && !read_length(in, in_end, literals)) return Lz4Status::Truncated;
        if (literals > static_cast<std::size_t>(in_end - in)) return Lz4Status::Truncated;
        if (literals > dst_size - out) return Lz4Status::OutputOverflow;
        std::memcpy(dst + out, in, literals);
        in += literals;
        out += literals;
        // The last sequence holds literals only: the input ends right after them.
        if (in == in_end) return out == dst_size ? Lz4Status::Ok : Lz4Status::SizeMismatch;
        if (in_end - in < 2) return Lz4Status::Truncated;
        const std::size_t offset = static_cast<std::size_t>(in[0]) | (static_cast<std::size_t>(in[1]) << 8);
        in += 2;
        if (offset == 0 || offset > out) return Lz4Status::BadOffset;
        std::size_t match = token & 15u;
        if (match == 15 && !read_length(in, in_end, match)) return Lz4Status::Truncated;
        match += 4;
        if (match > dst_size - out) return Lz4Status::OutputOverflow;
        // Byte by byte: a match may overlap its own output (offset < length repeats a run).
        const std::uint8_t* from = dst + out - offset;
        if (offset >= match) {
            std::memcpy(dst + out, from, match);
        } else {
            for (std::size_t i = 0; i < match; ++i) dst[out + i] = from[i];
        }
        out += match;
    }
}



namespace {

// Slicing-by-4 tables: four bytes per step keep verification well below the cost of
// reading and decompressing a block.
struct Crc32Tables {
    std::array<std::array<std::uint32_t, 256>, 4> t{};
    Crc32Tables() {
        for (std::uint32_t i = 0; i < 256; ++i) {
            std::uint32_t c = i;
            for (int k = 0; k < 8; ++k) c = (c & 1u) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
            t[0][i] = c;
        }
        for (std::uint32_t i = 0; i < 256; ++i) {
            for (std::size_t k = 1; k < 4; ++k) t[k][i] = (t[k - 1][i] >> 8) ^ t[0][t[k - 1][i] & 0xffu];
        }
    }
};

const Crc32Tables& tables() {
    static const Crc32Tables instance;
    return instance;
}

}  // namespace

std::uint32_t crc32(const std::uint8_t* data, std::size_t size, std::uint32_t crc) {
    const auto& t = tables().t;
    std::uint32_t c = ~crc;
    while (size >= 4) {
        c ^= static_cast<std::uint32_t>(data[0]) | static_cast<std::uint32_t>(data[1]) << 8 |
             static_cast<std::uint32_t>(data[2]) << 16 | static_cast<std::uint32_t>(data[3]) << 24;
        c = t[3][c & 0xffu] ^ t[2][(c >> 8) & 0xffu] ^ t[1][(c >> 16) & 0xffu] ^ t[0][c >> 24];
        data += 4;
        size -= 4;
    }
    while (size--) c = t[0][(c ^ *data++) & 0xffu] ^ (c >> 8);
    return ~c;
}

}  // namespace handwritten
