// The LZ4 block format (no frame) of the built models' 64 KB blocks (paper 000 §4.7: an
// LZ77-family codec, byte aligned, fast to decode), through liblz4: its safe decoder is
// fuzzed and well kept, and it decodes 2-3x faster than the decoder written here before
// (bench/results/decode.md).
#pragma once

#include <cstddef>
#include <cstdint>

namespace vastray {

enum class Lz4Status { Ok, Malformed, SizeMismatch };

const char* lz4_status_message(Lz4Status status);

// Decodes `src` into exactly `dst_size` bytes of `dst`. Never reads or writes out of
// bounds, whatever the input: corrupt data yields an error status, never a crash.
Lz4Status lz4_decompress_block(const std::uint8_t* src, std::size_t src_size, std::uint8_t* dst,
                               std::size_t dst_size);

// The largest compressed size of `size` input bytes.
std::size_t lz4_compress_bound(std::size_t size);

// LZ4's high-compression levels (LZ4_compress_HC): the same block format, decoded as
// fast, found by a slower search.
constexpr int kLz4HcMaxLevel = 12;

// Compresses `size` bytes (at most 64 KiB) into `dst`, which holds `capacity` bytes (at
// least lz4_compress_bound(size)); returns the compressed size. hc_level 0: the fast
// compressor, whose output equals lz4.block.compress(..., mode="default",
// store_size=False) of the same liblz4; 1 ... 12: LZ4 HC at that level.
std::size_t lz4_compress_block(const std::uint8_t* src, std::size_t size, std::uint8_t* dst, std::size_t capacity,
                               int hc_level = 0);

}  // namespace vastray
