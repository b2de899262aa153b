// What a fetcher thread does per block (read the stored bytes, check the CRC-32, decode
// the LZ4 block), timed stage by stage for each implementation side by side:
// vastray's former CRC-32 and LZ4 decoder (handwritten_codec.cpp) against zlib's and
// libdeflate's crc32 and liblz4's LZ4_decompress_safe, and the module's whole fetch.
//
//   decode_blocks MODEL.vast PASSES   ->  one JSON object on stdout
//
// Built and run by bench/decode.py; not part of the package.
#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <limits>
#include <map>
#include <string>
#include <vector>

#include <libdeflate.h>
#include <lz4.h>
#include <zlib.h>

#include "vastray/format.h"
#include "vastray/model_index.h"
#include "handwritten_codec.h"

using Clock = std::chrono::steady_clock;

namespace {

double seconds(const std::function<void()>& fn) {
    const auto t0 = Clock::now();
    fn();
    return std::chrono::duration<double>(Clock::now() - t0).count();
}

void read_all(int fd, const vastray::ModelIndex& index, std::vector<std::vector<std::uint8_t>>& stored) {
    for (std::size_t b = 0; b < index.block_count(); ++b) {
        const auto& e = index.entry(b);
        stored[b].resize(e.stored_size);
        std::size_t done = 0;
        while (done < e.stored_size) {
            const ssize_t n = ::pread(fd, stored[b].data() + done, e.stored_size - done, static_cast<off_t>(e.offset + done));
            if (n <= 0) {
                std::fprintf(stderr, "read failed\n");
                std::exit(1);
            }
            done += static_cast<std::size_t>(n);
        }
    }
}

}  // namespace

int main(int argc, char** argv) {
    if (argc < 3) {
        std::fprintf(stderr, "usage: %s MODEL.vast PASSES\n", argv[0]);
        return 2;
    }
    const vastray::ModelIndex index(argv[1]);
    const int passes = std::max(1, std::atoi(argv[2]));
    const int fd = ::open(argv[1], O_RDONLY);
    const std::size_t n = index.block_count();
    std::vector<std::vector<std::uint8_t>> stored(n);
    std::uint64_t stored_bytes = 0, raw_bytes = 0, lz4_blocks = 0, lz4_stored = 0, lz4_raw = 0;
    for (std::size_t b = 0; b < n; ++b) {
        const auto& e = index.entry(b);
        stored_bytes += e.stored_size;
        raw_bytes += e.raw_size;
        if (e.codec == vastray::format::kCodecLz4) {
            ++lz4_blocks;
            lz4_stored += e.stored_size;
            lz4_raw += e.raw_size;
        }
    }
    std::vector<std::uint8_t> out(vastray::format::kBlockSize);
    std::map<std::string, double> best;
    auto keep = [&](const std::string& name, double s) {
        auto it = best.find(name);
        if (it == best.end() || s < it->second) best[name] = s;
    };
    std::uint32_t sink = 0;  // keeps the checksums from being optimised away
    for (int pass = 0; pass < passes; ++pass) {
        // Cold: the model's pages dropped from the page cache, as on a server's first view.
        ::posix_fadvise(fd, 0, 0, POSIX_FADV_DONTNEED);
        keep("read_cold", seconds([&] { read_all(fd, index, stored); }));
        keep("read_warm", seconds([&] { read_all(fd, index, stored); }));
        keep("crc_vastray", seconds([&] {
            for (const auto& s : stored) sink ^= handwritten::crc32(s.data(), s.size());
        }));
        keep("crc_zlib", seconds([&] {
            for (const auto& s : stored) sink ^= static_cast<std::uint32_t>(::crc32(0L, s.data(), static_cast<uInt>(s.size())));
        }));
        keep("crc_libdeflate", seconds([&] {
            for (const auto& s : stored) sink ^= libdeflate_crc32(0, s.data(), s.size());
        }));
        keep("lz4_vastray", seconds([&] {
            for (std::size_t b = 0; b < n; ++b) {
                const auto& e = index.entry(b);
                if (e.codec != vastray::format::kCodecLz4) continue;
                if (handwritten::lz4_decompress_block(stored[b].data(), e.stored_size, out.data(), e.raw_size) !=
                    handwritten::Lz4Status::Ok) {
                    std::fprintf(stderr, "vastray decoder failed on block %zu\n", b);
                    std::exit(1);
                }
                sink ^= out[e.raw_size / 2];
            }
        }));
        keep("lz4_liblz4", seconds([&] {
            for (std::size_t b = 0; b < n; ++b) {
                const auto& e = index.entry(b);
                if (e.codec != vastray::format::kCodecLz4) continue;
                const int got = LZ4_decompress_safe(reinterpret_cast<const char*>(stored[b].data()),
                                                    reinterpret_cast<char*>(out.data()), static_cast<int>(e.stored_size),
                                                    static_cast<int>(e.raw_size));
                if (got != static_cast<int>(e.raw_size)) {
                    std::fprintf(stderr, "liblz4 failed on block %zu\n", b);
                    std::exit(1);
                }
                sink ^= out[e.raw_size / 2];
            }
        }));
        // The whole fetch as the block cache does it, through the module's own code.
        std::vector<std::uint8_t> scratch;
        keep("fetch_module", seconds([&] {
            for (std::size_t b = 0; b < n; ++b) {
                const std::string error = index.read_block(b, out.data(), scratch);
                if (!error.empty()) {
                    std::fprintf(stderr, "%s\n", error.c_str());
                    std::exit(1);
                }
            }
        }));
    }
    std::printf("{\"blocks\": %zu, \"lz4_blocks\": %llu, \"stored_bytes\": %llu, \"raw_bytes\": %llu, "
                "\"lz4_stored_bytes\": %llu, \"lz4_raw_bytes\": %llu, \"passes\": %d, \"check\": %u",
                n, static_cast<unsigned long long>(lz4_blocks), static_cast<unsigned long long>(stored_bytes),
                static_cast<unsigned long long>(raw_bytes), static_cast<unsigned long long>(lz4_stored),
                static_cast<unsigned long long>(lz4_raw), passes, sink & 1u);
    for (const auto& [name, s] : best) std::printf(", \"%s_s\": %.9f", name.c_str(), s);
    std::printf("}\n");
    ::close(fd);
    return 0;
}
