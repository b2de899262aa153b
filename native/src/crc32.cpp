#include "vastray/crc32.h"

#include <libdeflate.h>

namespace vastray {

std::uint32_t crc32(const std::uint8_t* data, std::size_t size, std::uint32_t crc) {
    return libdeflate_crc32(crc, data, size);
}

}  // namespace vastray
