// Decoder for the LZ4 block format (no frame), used to read the compressed 64 KB blocks
// of built models (paper 000 §4.7: an LZ77-family codec, byte aligned, fast to decode).
// Written against the public format description so the reader needs no codec library;
// the writer side uses the `lz4` Python package, and tests cross-check the two.
#pragma once

#include <cstddef>
#include <cstdint>

namespace vastray {

enum class Lz4Status { Ok, Truncated, BadOffset, OutputOverflow, SizeMismatch };

const char* lz4_status_message(Lz4Status status);

// Decodes `src` into exactly `dst_size` bytes of `dst`. Never reads or writes out of
// bounds, whatever the input: corrupt data yields an error status, never a crash.
Lz4Status lz4_decompress_block(const std::uint8_t* src, std::size_t src_size, std::uint8_t* dst,
                               std::size_t dst_size);

}  // namespace vastray
