// CRC-32 as zlib and PNG define it (reflected 0xEDB88320, init and final XOR 0xFFFFFFFF):
// the checksum of every stored block and of the model header and index.
#pragma once

#include <cstddef>
#include <cstdint>

namespace vastray {

// `crc` continues a running checksum; start with 0 (as zlib.crc32 does).
std::uint32_t crc32(const std::uint8_t* data, std::size_t size, std::uint32_t crc = 0);

}  // namespace vastray
