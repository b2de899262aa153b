// The baseline of bench/decode.py: vastray's former CRC-32 and LZ4 block decoder.
#pragma once

#include <cstddef>
#include <cstdint>

namespace handwritten {

enum class Lz4Status { Ok, Truncated, BadOffset, OutputOverflow, SizeMismatch };

const char* lz4_status_message(Lz4Status status);

// Decodes `src` into exactly `dst_size` bytes of `dst`, never out of bounds.
Lz4Status lz4_decompress_block(const std::uint8_t* src, std::size_t src_size, std::uint8_t* dst,
                               std::size_t dst_size);

// zlib's CRC-32 (slicing by 4); `crc` continues a running checksum.
std::uint32_t crc32(const std::uint8_t* data, std::size_t size, std::uint32_t crc = 0);

}  // namespace handwritten
