// Appends bytes to a file past the page cache (O_DIRECT), from a 4 KiB-aligned offset:
// how a build's blocks go into the model file as they are made. Written where they end
// up, they need no copy in the write phase, and no page-cache memory that the kernel must
// first find and clear (bench/results/firsttouch.md). A thread of its own writes each
// full buffer while the next one fills, so the emission never waits on the disk unless
// the disk is slower than it.
#pragma once

#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <mutex>
#include <string>
#include <thread>

namespace vastray::writer {

class DirectAppender {
public:
    // Opens (creates) `path` and appends from `start`, a multiple of kAlign; what lies
    // before `start` is left alone. Where the file system refuses O_DIRECT (at open or at
    // a write) the same writes go through the page cache.
    DirectAppender(std::string path, std::uint64_t start);
    ~DirectAppender();
    DirectAppender(const DirectAppender&) = delete;
    DirectAppender& operator=(const DirectAppender&) = delete;

    // Where the next byte goes.
    std::uint64_t position() const { return offset_ + fill_; }
    // Throws std::runtime_error naming the file when an earlier write failed.
    void append(const std::uint8_t* data, std::size_t n);
    // Writes what is left, its last 4 KiB page padded with zeros past position(), and
    // closes the file (not synced: the caller goes on appending and syncs at the end).
    void finish();
    bool direct() const { return direct_; }

    static constexpr std::size_t kAlign = 4096;
    static constexpr std::size_t kBuffer = 8u << 20;

private:
    void write_out(const std::uint8_t* data, std::size_t n, std::uint64_t at);
    void writer_loop();
    void hand_over();  // the full front buffer to the writer thread
    void wait_idle(std::unique_lock<std::mutex>& lock);

    std::string path_;
    int fd_ = -1;
    bool direct_ = false;
    std::uint8_t* buffers_[2] = {nullptr, nullptr};
    std::uint8_t* front_ = nullptr;  // filled by append()
    std::size_t fill_ = 0;
    std::uint64_t offset_ = 0;  // file offset of front_[0]

    std::mutex mutex_;
    std::condition_variable changed_;
    const std::uint8_t* pending_ = nullptr;  // handed to the writer thread, not yet written
    std::size_t pending_size_ = 0;
    std::uint64_t pending_at_ = 0;
    bool stop_ = false;
    std::string failure_;
    std::thread writer_;
};

}  // namespace vastray::writer
