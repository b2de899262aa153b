// When the renderers keep several packets in flight (traverse_packets in core,
// lod_trace_packets out of core): a packet that stops where its next load would miss
// pays only when the data it walks is far larger than the caches. Below that the pauses
// cost more than the overlapped misses save. Measured one thread, one packet at a time
// against 8 in flight: in core, plant 3*10^6 (a 175 MiB tree) 1.06x, 10^7 1.18-1.21x,
// 10^6 (60 MiB) 0.95x; out of core, 720p overviews at PoE 2, plant 10^8 (a 4 GiB file)
// 1.12-1.16x, 10^7 (400 MiB) 1.03-1.04x, 10^6 (39 MiB) 0.92x.
#pragma once

#include <cctype>
#include <cerrno>
#include <cstdint>
#include <cstdlib>
#include <stdexcept>
#include <string>

namespace vastray {

constexpr std::uint64_t kInterleaveBytes = std::uint64_t{128} << 20;

// Whether to interleave over data of `bytes` (an in-core tree, a model file): from
// kInterleaveBytes, or from VASTRAY_INTERLEAVE_BYTES when set (0: always), for tests
// and studies.
inline bool interleaves(std::uint64_t bytes) {
    std::uint64_t from = kInterleaveBytes;
    const char* env = std::getenv("VASTRAY_INTERLEAVE_BYTES");
    if (env != nullptr && *env != '\0') {
        char* end = nullptr;
        errno = 0;
        const unsigned long long value = std::strtoull(env, &end, 10);
        if (*end != '\0' || errno != 0 || !std::isdigit(static_cast<unsigned char>(env[0]))) {
            throw std::invalid_argument("VASTRAY_INTERLEAVE_BYTES must be a number of bytes (got '" +
                                        std::string(env) + "')");
        }
        from = value;
    }
    return bytes >= from;
}

}  // namespace vastray
