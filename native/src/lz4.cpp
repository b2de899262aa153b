#include "vastray/lz4.h"

#include <cstring>

namespace vastray {

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

}  // namespace vastray
