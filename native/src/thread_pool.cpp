#include "vastray/thread_pool.h"

#include <cstdlib>
#include <string>
#include <utility>

#if defined(__linux__)
#include <sched.h>
#endif

namespace vastray {

unsigned hardware_threads() {
    if (const char* env = std::getenv("VASTRAY_THREADS")) {
        const long n = std::strtol(env, nullptr, 10);
        if (n > 0) return static_cast<unsigned>(n);
    }
#if defined(__linux__)
    // The CPUs this process may run on: a container's cpuset or a taskset, where
    // hardware_concurrency() counts every CPU of the host and the pool would oversubscribe.
    cpu_set_t set;
    CPU_ZERO(&set);
    if (sched_getaffinity(0, sizeof(set), &set) == 0) {
        const int n = CPU_COUNT(&set);
        if (n > 0) return static_cast<unsigned>(n);
    }
#endif
    const unsigned n = std::thread::hardware_concurrency();
    return n == 0 ? 1 : n;
}

ThreadPool::ThreadPool(unsigned threads) {
    const unsigned lanes = threads == 0 ? hardware_threads() : threads;
    for (unsigned lane = 1; lane < lanes; ++lane) {
        workers_.emplace_back([this, lane] { worker_loop(lane); });
    }
}

ThreadPool::~ThreadPool() {
    {
        std::lock_guard<std::mutex> lock(mutex_);
        stop_ = true;
    }
    wake_.notify_all();
    for (auto& t : workers_) t.join();
}

ThreadPool& ThreadPool::global() {
    static ThreadPool pool;
    return pool;
}

namespace {
thread_local bool t_in_task = false;
}  // namespace

bool ThreadPool::in_task() { return t_in_task; }

void ThreadPool::run_lane(unsigned lane) {
    if (lane >= job_lanes_) return;
    struct InTask {
        InTask() { t_in_task = true; }
        ~InTask() { t_in_task = false; }
    } in_task;
    for (;;) {
        const std::size_t task = next_.fetch_add(1, std::memory_order_relaxed);
        if (task >= job_count_) break;
        try {
            (*job_)(task, lane);
        } catch (...) {
            std::lock_guard<std::mutex> lock(mutex_);
            if (!error_) error_ = std::current_exception();
            // Drain the remaining tasks so every lane stops promptly.
            next_.store(job_count_, std::memory_order_relaxed);
        }
    }
}

void ThreadPool::worker_loop(unsigned lane) {
    std::uint64_t seen = 0;
    for (;;) {
        {
            std::unique_lock<std::mutex> lock(mutex_);
            wake_.wait(lock, [&] { return stop_ || generation_ != seen; });
            if (stop_) return;
            seen = generation_;
        }
        run_lane(lane);
        {
            std::lock_guard<std::mutex> lock(mutex_);
            if (--active_ == 0) done_.notify_all();
        }
    }
}

void ThreadPool::parallel_for(std::size_t count,
                              const std::function<void(std::size_t, unsigned)>& fn,
                              unsigned max_lanes) {
    if (count == 0) return;
    std::lock_guard<std::mutex> job_lock(job_mutex_);
    {
        std::lock_guard<std::mutex> lock(mutex_);
        job_ = &fn;
        job_count_ = count;
        job_lanes_ = max_lanes == 0 ? lanes() : std::min(max_lanes, lanes());
        error_ = nullptr;
        next_.store(0, std::memory_order_relaxed);
        active_ = static_cast<unsigned>(workers_.size());
        ++generation_;
    }
    wake_.notify_all();
    run_lane(0);
    std::exception_ptr error;
    {
        std::unique_lock<std::mutex> lock(mutex_);
        done_.wait(lock, [&] { return active_ == 0; });
        job_ = nullptr;
        // Take the error out: a kept exception_ptr would live on in this static pool
        // until exit, and one that wraps a Python error must die while Python does.
        error = std::exchange(error_, nullptr);
    }
    if (error) std::rethrow_exception(error);
}

}  // namespace vastray
