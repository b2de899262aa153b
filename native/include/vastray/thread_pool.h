// A fixed pool of worker threads for data-parallel loops (render tiles, batch queries).
// The calling thread takes part in the work, so a pool of N workers runs N+1 lanes.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <exception>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

namespace vastray {

class ThreadPool {
public:
    // threads == 0 means one lane per hardware thread.
    explicit ThreadPool(unsigned threads = 0);
    ~ThreadPool();
    ThreadPool(const ThreadPool&) = delete;
    ThreadPool& operator=(const ThreadPool&) = delete;

    unsigned lanes() const { return static_cast<unsigned>(workers_.size()) + 1; }

    // Calls fn(task, lane) for task in [0, count); lane in [0, lanes) identifies the
    // executing lane so callers can keep per-lane scratch data without locks.
    // Tasks are handed out dynamically (atomic counter): load balances across tiles.
    // max_lanes (0 = all) caps how many lanes take part, for scaling measurements.
    // The first exception thrown by fn is rethrown here after all lanes stop.
    void parallel_for(std::size_t count, const std::function<void(std::size_t, unsigned)>& fn,
                      unsigned max_lanes = 0);

    // The process-wide pool, sized to the hardware (VASTRAY_THREADS overrides).
    static ThreadPool& global();

    // Whether the calling thread is running a task of some pool's parallel_for: a
    // parallel_for from there would wait for itself.
    static bool in_task();

private:
    void worker_loop(unsigned lane);
    void run_lane(unsigned lane);

    std::vector<std::thread> workers_;
    std::mutex mutex_;
    std::mutex job_mutex_;  // one parallel_for at a time; concurrent callers queue here
    std::condition_variable wake_;
    std::condition_variable done_;
    const std::function<void(std::size_t, unsigned)>* job_ = nullptr;
    std::size_t job_count_ = 0;
    unsigned job_lanes_ = 0;
    std::exception_ptr error_;
    std::atomic<std::size_t> next_{0};
    unsigned active_ = 0;
    std::uint64_t generation_ = 0;
    bool stop_ = false;
};

unsigned hardware_threads();

}  // namespace vastray
