#include "writer/direct_appender.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <utility>

namespace vastray::writer {

DirectAppender::DirectAppender(std::string path, std::uint64_t start) : path_(std::move(path)), offset_(start) {
    if (start % kAlign) throw std::invalid_argument("a direct append starts at a multiple of 4096 bytes");
    const int flags = O_WRONLY | O_CREAT | O_CLOEXEC;
#ifdef O_DIRECT
    fd_ = ::open(path_.c_str(), flags | O_DIRECT, 0644);
    direct_ = fd_ >= 0;
    if (fd_ < 0 && errno != EINVAL) throw std::runtime_error(path_ + ": cannot create: " + std::strerror(errno));
#endif
    if (fd_ < 0) fd_ = ::open(path_.c_str(), flags, 0644);
    if (fd_ < 0) throw std::runtime_error(path_ + ": cannot create: " + std::strerror(errno));
    for (auto& b : buffers_) {
        b = static_cast<std::uint8_t*>(std::aligned_alloc(kAlign, kBuffer));
        if (b == nullptr) {
            ::close(fd_);
            std::free(buffers_[0]);
            throw std::bad_alloc();
        }
    }
    front_ = buffers_[0];
    writer_ = std::thread([this] { writer_loop(); });
}

DirectAppender::~DirectAppender() {
    {
        std::lock_guard<std::mutex> lock(mutex_);
        stop_ = true;
    }
    changed_.notify_all();
    if (writer_.joinable()) writer_.join();
    if (fd_ >= 0) ::close(fd_);
    for (auto* b : buffers_) std::free(b);
}

void DirectAppender::append(const std::uint8_t* data, std::size_t n) {
    while (n > 0) {
        const std::size_t take = std::min(n, kBuffer - fill_);
        std::memcpy(front_ + fill_, data, take);
        fill_ += take;
        data += take;
        n -= take;
        if (fill_ == kBuffer) hand_over();
    }
}

void DirectAppender::hand_over() {
    std::unique_lock<std::mutex> lock(mutex_);
    wait_idle(lock);
    pending_ = front_;
    pending_size_ = fill_;
    pending_at_ = offset_;
    lock.unlock();
    changed_.notify_all();
    front_ = front_ == buffers_[0] ? buffers_[1] : buffers_[0];
    offset_ += fill_;
    fill_ = 0;
}

void DirectAppender::wait_idle(std::unique_lock<std::mutex>& lock) {
    changed_.wait(lock, [&] { return pending_ == nullptr; });
    if (!failure_.empty()) throw std::runtime_error(failure_);
}

void DirectAppender::finish() {
    if (fd_ < 0) return;
    // The last page goes out whole; the bytes past position() are zeros that the next
    // writer overwrites or cuts off.
    const std::size_t padded = (fill_ + kAlign - 1) / kAlign * kAlign;
    std::memset(front_ + fill_, 0, padded - fill_);
    {
        std::unique_lock<std::mutex> lock(mutex_);
        wait_idle(lock);
        if (padded > 0) {
            pending_ = front_;
            pending_size_ = padded;
            pending_at_ = offset_;
        }
        stop_ = true;
    }
    changed_.notify_all();
    writer_.join();
    const int closed = ::close(fd_);
    fd_ = -1;
    if (!failure_.empty()) throw std::runtime_error(failure_);
    if (closed != 0) throw std::runtime_error(path_ + ": write failed: " + std::strerror(errno));
}

void DirectAppender::writer_loop() {
    std::unique_lock<std::mutex> lock(mutex_);
    for (;;) {
        changed_.wait(lock, [&] { return pending_ != nullptr || stop_; });
        if (pending_ == nullptr) return;
        const std::uint8_t* data = pending_;
        const std::size_t n = pending_size_;
        const std::uint64_t at = pending_at_;
        lock.unlock();
        std::string failed;
        try {
            write_out(data, n, at);
        } catch (const std::exception& e) {
            failed = e.what();
        }
        lock.lock();
        if (!failed.empty() && failure_.empty()) failure_ = failed;
        pending_ = nullptr;
        changed_.notify_all();
    }
}

void DirectAppender::write_out(const std::uint8_t* data, std::size_t n, std::uint64_t at) {
    std::size_t done = 0;
    while (done < n) {
        const ssize_t w = ::pwrite(fd_, data + done, n - done, static_cast<off_t>(at + done));
        if (w < 0 && errno == EINTR) continue;
        if (w < 0 && errno == EINVAL && direct_) {
            // The file system took the flag at open but refuses direct writes: go on
            // through the page cache.
#ifdef O_DIRECT
            ::fcntl(fd_, F_SETFL, ::fcntl(fd_, F_GETFL) & ~O_DIRECT);
#endif
            direct_ = false;
            continue;
        }
        if (w < 0) throw std::runtime_error(path_ + ": write failed: " + std::strerror(errno));
        if (w == 0) throw std::runtime_error(path_ + ": write failed: the disk took nothing");
        done += static_cast<std::size_t>(w);
    }
}

}  // namespace vastray::writer
