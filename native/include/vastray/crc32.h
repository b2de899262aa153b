// CRC-32 as zlib and PNG define it (reflected 0xEDB88320, init and final XOR 0xFFFFFFFF):
// the checksum of every stored block and of the model header and index. Computed by
// libdeflate, which picks a carry-less-multiply kernel at run time where the CPU has
// one: 7x the slicing-by-4 tables written here before (bench/results/decode.md).
#pragma once

#include <cstddef>
#include <cstdint>

namespace vastray {

// `crc` continues a running checksum; start with 0 (as zlib.crc32 does).
std::uint32_t crc32(const std::uint8_t* data, std::size_t size, std::uint32_t crc = 0);

}  // namespace vastray
