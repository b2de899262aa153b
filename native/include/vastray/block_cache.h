// The process-wide block cache (paper 000 §5, paper 003 §4): a byte budget cut into
// fixed 64 KB slots, shared by every open model and every concurrent render.
//
// Render threads never lock. A frame looks blocks up in a per-model table of atomics,
// stamps the slots it uses, and counts requests for the blocks it misses in per-block
// atomics. Everything else happens at the two synchronisation points of a frame, under
// the cache mutex:
//   begin_frame  publishes the blocks the fetchers finished since the last frame;
//   end_frame    queues the frame's requests by priority (bounded per frame) and
//                evicts least-recently-used blocks the current working set does not use,
//                so the fetchers have free slots.
// Fetcher threads read, verify and decode blocks into free slots that no table points
// at, so no frame ever sees a block change under it. An evicted slot is reused only
// after every frame that was running when it was evicted has ended (epoch reclamation),
// so even a concurrent frame that looked the block up just before it left the table
// reads valid bytes.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "vastray/format.h"
#include "vastray/frame_stats.h"
#include "vastray/model_index.h"

namespace vastray {

class BlockCache;

enum class FetchPriority {
    RequestCount,   // paper 000 §5.3: rays that asked for the block this frame
    ProjectedSize,  // paper 003: the largest projected size of a voxel that wanted it
};

// A model registered with a cache. Render threads use lookup/request; the cache owns
// the state behind them.
class CachedModel {
public:
    static constexpr std::int32_t kAbsent = -1;
    static constexpr std::int32_t kBad = -2;  // failed to read or verify: never requested again

    const ModelIndex& index() const { return *index_; }
    std::uint32_t id() const { return id_; }

    // Slot index of a resident block, kAbsent or kBad. Lock-free.
    std::int32_t slot(std::uint32_t block) const { return slot_of_[block].load(std::memory_order_acquire); }

    // Records that a ray wanted a missing block. Returns true for the first request of
    // this block since the cache last collected requests (the caller remembers it).
    bool request(std::uint32_t block, float projected_size) {
        std::uint32_t bits;
        static_assert(sizeof bits == sizeof projected_size);
        std::memcpy(&bits, &projected_size, sizeof bits);
        // Positive floats order like their bit patterns: an integer max keeps the largest.
        std::uint32_t seen = max_size_[block].load(std::memory_order_relaxed);
        while (bits > seen && !max_size_[block].compare_exchange_weak(seen, bits, std::memory_order_relaxed)) {
        }
        return requests_[block].fetch_add(1, std::memory_order_relaxed) == 0;
    }

private:
    friend class BlockCache;
    CachedModel(std::shared_ptr<const ModelIndex> index, std::uint32_t id);

    enum class State : std::uint8_t { Absent, Queued, Loading, Ready, Resident, Bad };

    std::shared_ptr<const ModelIndex> index_;
    std::uint32_t id_;
    std::unique_ptr<std::atomic<std::int32_t>[]> slot_of_;
    std::unique_ptr<std::atomic<std::uint32_t>[]> requests_, max_size_;
    std::vector<State> state_;  // under the cache mutex
    std::vector<std::string> errors_;  // under the cache mutex
    std::size_t loading_ = 0;          // under the cache mutex
    bool closed_ = false;              // under the cache mutex
};

struct CacheConfig {
    std::size_t budget_bytes = std::size_t{1} << 30;
    unsigned fetchers = 2;
    FetchPriority priority = FetchPriority::RequestCount;
    std::size_t max_requests_per_frame = 256;  // the fetch list a frame may add to
    std::size_t max_pending = 4096;            // requests older than this many are dropped
    // Requests within a factor of two in priority are fetched in file order (false:
    // strictly by priority, then arrival).
    bool file_order = true;
    // Back the slots with 2 MiB transparent huge pages where the kernel offers them
    // (madvise mode): a frame's rays touch blocks all over a working set of gigabytes,
    // and with 4 KiB pages nearly every block a ray enters costs a TLB miss as well as
    // a cache miss (Embree's `hugepages` option does the same for its BVH).
    bool huge_pages = true;
    // Tell the kernel which blocks a frame queued (POSIX_FADV_WILLNEED), so it reads them
    // ahead, many at once, while the fetchers still work through earlier ones: a
    // fetcher's pread then finds them in the page cache. Two fetchers alone keep only two
    // reads in flight, a third of a disk's rate (bench/results/complete.md).
    bool readahead = true;
};

// The slots' memory: one anonymous mapping, untouched (and so not resident) until a
// block lands in it; 2 MiB-aligned with MADV_HUGEPAGE when asked for.
class SlotArena {
public:
    SlotArena(std::size_t bytes, bool huge_pages);
    ~SlotArena();
    SlotArena(const SlotArena&) = delete;
    SlotArena& operator=(const SlotArena&) = delete;
    std::uint8_t* get() const { return data_; }
    bool huge_pages() const { return huge_; }  // the kernel accepted the advice

private:
    std::uint8_t* data_ = nullptr;  // the slots (the mapping), 2 MiB-aligned when huge
    std::size_t mapped_ = 0;
    bool huge_ = false;
};

struct CacheTotals {
    std::size_t budget_bytes = 0, slot_count = 0, resident_blocks = 0, resident_bytes = 0;
    std::size_t free_slots = 0, retired_slots = 0, pending = 0, loading = 0, ready = 0;
    std::uint64_t loaded = 0, evicted = 0, failed = 0, bytes_read = 0;
    unsigned fetchers = 0;
    std::size_t models = 0, active_frames = 0;
};

class BlockCache {
public:
    static constexpr std::size_t kSlotBytes = format::kBlockSize;

    explicit BlockCache(const CacheConfig& config);
    ~BlockCache();
    BlockCache(const BlockCache&) = delete;
    BlockCache& operator=(const BlockCache&) = delete;

    const CacheConfig& config() const { return config_; }
    std::size_t slot_count() const { return slot_count_; }
    bool huge_pages() const { return arena_->huge_pages(); }  // the slots are on transparent huge pages

    // Registers a model. Its top level (the root treelet) is loaded before this returns,
    // so the first frame always has the coarsest voxels to show.
    std::shared_ptr<CachedModel> add_model(std::shared_ptr<const ModelIndex> index);
    // Drops a model's queued requests and frees its slots once no frame can use them.
    void remove_model(const std::shared_ptr<CachedModel>& model);

    // Loads blocks synchronously (for opening a model: the coarse levels). It may evict
    // blocks no frame used since the last frame began, never ones loaded by this call;
    // blocks that still do not fit are skipped. Returns how many were loaded.
    std::size_t preload(CachedModel& model, const std::vector<std::uint32_t>& blocks);

    // Frame protocol. begin_frame returns the frame's tick (stamps and epochs).
    std::uint32_t begin_frame(FrameCacheStats& stats);
    // `requests`: the (model, block) pairs this frame asked for first. `limit` bounds how
    // many of them join the fetch queue (0: max_requests_per_frame).
    void end_frame(std::uint32_t tick, const std::vector<std::pair<CachedModel*, std::uint32_t>>& requests,
                   FrameCacheStats& stats, std::size_t limit = 0);

    // Slot bytes (valid for the frame that looked the slot up).
    const std::uint8_t* slot_data(std::int32_t slot) const { return slot_bytes(slot); }
    // Marks a slot used by frame `tick`; true when this is the frame's first use of it.
    // Two stamps: `last_used_` orders eviction (publishing sets it too, to protect fresh
    // blocks), `seen_` only records use, so working sets count exactly what frames read.
    bool touch(std::int32_t slot, std::uint32_t tick) {
        const auto s = static_cast<std::size_t>(slot);
        if (seen_[s].load(std::memory_order_relaxed) == tick) return false;
        if (last_used_[s].load(std::memory_order_relaxed) != tick) last_used_[s].store(tick, std::memory_order_relaxed);
        return seen_[s].exchange(tick, std::memory_order_relaxed) != tick;
    }
    std::uint32_t slot_raw_size(std::int32_t slot) const { return slot_raw_[static_cast<std::size_t>(slot)]; }

    // Blocks until a fetch finishes or `timeout_ms` passes; true if something finished
    // (or nothing is pending, so waiting longer would not help).
    bool wait_for_fetches(double timeout_ms);
    // Blocks until nothing is queued or loading (tests and benchmarks).
    void drain();
    // Blocks until nothing is queued or loading, or `timeout_ms` passes; true if idle.
    bool wait_idle(double timeout_ms);

    CacheTotals totals() const;
    // Resident blocks of a model with the tick of the frame that last used each (tests,
    // tools): (block, tick) pairs in block order.
    std::vector<std::pair<std::uint32_t, std::uint32_t>> resident(const CachedModel& model) const;
    // Errors met reading a model's blocks ("block 12 (level 3): checksum mismatch ...").
    std::vector<std::string> model_errors(const CachedModel& model) const;
    // Checks the bookkeeping (each slot free, retired or owned exactly once; tables
    // point at owned slots). Returns an empty string when consistent.
    std::string check_invariants() const;

private:
    struct Request {
        CachedModel* model;
        std::uint32_t block;
        float priority;
        std::uint64_t serial;  // order of arrival, for ageing out old requests
    };
    struct Finished {
        CachedModel* model;
        std::uint32_t block;
        std::int32_t slot;
    };
    struct Retired {
        std::int32_t slot;
        std::uint32_t tick;
    };

    void fetcher_loop();
    void reclaim_locked();
    void forget_if_closed_locked(CachedModel& model);
    std::size_t evict_locked(std::size_t wanted, std::uint32_t protect_from);
    void publish_locked(FrameCacheStats* stats);
    std::uint8_t* slot_bytes(std::int32_t slot) const {
        return arena_->get() + static_cast<std::size_t>(slot) * kSlotBytes;
    }
    using Readahead = std::vector<std::pair<std::shared_ptr<const ModelIndex>, std::uint32_t>>;
    void end_frame_locked(std::uint32_t tick, const std::vector<std::pair<CachedModel*, std::uint32_t>>& requests,
                          FrameCacheStats& stats, std::size_t limit, Readahead& readahead);

    CacheConfig config_;
    std::size_t slot_count_;
    std::unique_ptr<SlotArena> arena_;
    std::unique_ptr<std::atomic<std::uint32_t>[]> last_used_, seen_;
    std::vector<std::uint32_t> slot_raw_;        // raw bytes in each slot
    std::vector<CachedModel*> slot_model_;       // owner of each slot (null: free or loading)
    std::vector<std::uint32_t> slot_block_;

    mutable std::mutex mutex_;
    std::condition_variable work_;   // fetchers wait here
    std::condition_variable done_;   // wait_for_fetches/drain wait here
    std::vector<std::int32_t> free_slots_;
    std::vector<Retired> retired_;
    std::vector<Request> pending_;   // sorted by priority class, then file order; best last
    std::vector<Finished> ready_;
    std::vector<std::uint32_t> active_ticks_;  // ticks of frames between begin and end
    std::vector<std::shared_ptr<CachedModel>> models_;
    std::uint32_t tick_ = 0;
    std::uint64_t serial_ = 0, fetch_generation_ = 0;
    std::size_t loading_ = 0;
    std::uint64_t loaded_total_ = 0, evicted_total_ = 0, failed_total_ = 0, bytes_read_ = 0;
    std::uint32_t next_model_id_ = 0;
    bool stop_ = false;
    std::vector<std::thread> fetchers_;
};

}  // namespace vastray
