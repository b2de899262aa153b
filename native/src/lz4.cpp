#include "vastray/lz4.h"

#include <lz4.h>
#include <lz4hc.h>

#include <limits>
#include <stdexcept>

namespace vastray {

const char* lz4_status_message(Lz4Status status) {
    switch (status) {
        case Lz4Status::Ok: return "ok";
        case Lz4Status::Malformed: return "the decoder rejects the data (damaged or truncated)";
        case Lz4Status::SizeMismatch: return "decoded size differs from the expected size";
    }
    return "unknown error";
}

Lz4Status lz4_decompress_block(const std::uint8_t* src, std::size_t src_size, std::uint8_t* dst,
                               std::size_t dst_size) {
    constexpr auto kMax = static_cast<std::size_t>(std::numeric_limits<int>::max());
    if (src_size > kMax || dst_size > kMax) return Lz4Status::Malformed;
    if (src_size == 0) return dst_size == 0 ? Lz4Status::Ok : Lz4Status::Malformed;
    const int got = LZ4_decompress_safe(reinterpret_cast<const char*>(src), reinterpret_cast<char*>(dst),
                                        static_cast<int>(src_size), static_cast<int>(dst_size));
    if (got < 0) return Lz4Status::Malformed;
    return static_cast<std::size_t>(got) == dst_size ? Lz4Status::Ok : Lz4Status::SizeMismatch;
}

std::size_t lz4_compress_bound(std::size_t size) {
    return static_cast<std::size_t>(LZ4_compressBound(static_cast<int>(size)));
}

std::size_t lz4_compress_block(const std::uint8_t* src, std::size_t size, std::uint8_t* dst, std::size_t capacity,
                               int hc_level) {
    if (size > (1u << 16) || capacity < lz4_compress_bound(size)) throw std::invalid_argument("lz4_compress_block: bad sizes");
    if (hc_level < 0 || hc_level > kLz4HcMaxLevel) throw std::invalid_argument("lz4_compress_block: bad HC level");
    const auto* in = reinterpret_cast<const char*>(src);
    auto* out = reinterpret_cast<char*>(dst);
    const int n = hc_level == 0 ? LZ4_compress_default(in, out, static_cast<int>(size), static_cast<int>(capacity))
                                : LZ4_compress_HC(in, out, static_cast<int>(size), static_cast<int>(capacity), hc_level);
    if (n <= 0 && size > 0) throw std::runtime_error("LZ4 compression failed");
    return static_cast<std::size_t>(n);
}

}  // namespace vastray
