#include "vastray/crc32.h"

#include <array>

namespace vastray {

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

}  // namespace vastray
