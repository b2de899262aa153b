#include "vastray/block_cache.h"
#include "vastray/huge_pages.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <new>
#include <stdexcept>

#include <sys/mman.h>

namespace vastray {

CachedModel::CachedModel(std::shared_ptr<const ModelIndex> index, std::uint32_t id)
    : index_(std::move(index)), id_(id) {
    const std::size_t n = index_->block_count();
    slot_of_.reset(new std::atomic<std::int32_t>[n]);
    requests_.reset(new std::atomic<std::uint32_t>[n]);
    max_size_.reset(new std::atomic<std::uint32_t>[n]);
    for (std::size_t i = 0; i < n; ++i) {
        slot_of_[i].store(kAbsent, std::memory_order_relaxed);
        requests_[i].store(0, std::memory_order_relaxed);
        max_size_[i].store(0, std::memory_order_relaxed);
    }
    state_.assign(n, State::Absent);
}

SlotArena::SlotArena(std::size_t bytes, bool huge_pages) {
    // Whole huge pages either way, 2 MiB-aligned and advised when asked for.
    mapped_ = ::vastray::huge_pages::mapped_size(bytes);
    void* p = huge_pages ? ::vastray::huge_pages::map(bytes, MAP_NORESERVE, &huge_)
                         : mmap(nullptr, mapped_, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE,
                                -1, 0);
    if (p == nullptr || p == MAP_FAILED) throw std::bad_alloc();
    data_ = static_cast<std::uint8_t*>(p);
}

SlotArena::~SlotArena() { munmap(data_, mapped_); }

BlockCache::BlockCache(const CacheConfig& config) : config_(config) {
    slot_count_ = config.budget_bytes / kSlotBytes;
    if (slot_count_ < 4) throw std::invalid_argument("cache budget must hold at least 4 blocks of 64 KiB (256 KiB)");
    if (config.fetchers < 1 || config.fetchers > 64) throw std::invalid_argument("fetchers must be in [1, 64]");
    if (config.max_requests_per_frame < 1 || config.max_pending < config.max_requests_per_frame) {
        throw std::invalid_argument("max_pending must be at least max_requests_per_frame, which must be positive");
    }
    // One spare slot of padding: a damaged node can point a little past its block's end,
    // and the traversal's reads must stay inside memory we own. Pages are only touched
    // when a block lands in them, so resident memory grows with use, never past the budget.
    arena_ = std::make_unique<SlotArena>((slot_count_ + 1) * kSlotBytes, config.huge_pages);
    last_used_.reset(new std::atomic<std::uint32_t>[slot_count_]);
    seen_.reset(new std::atomic<std::uint32_t>[slot_count_]);
    for (std::size_t s = 0; s < slot_count_; ++s) {
        last_used_[s].store(0, std::memory_order_relaxed);
        seen_[s].store(0, std::memory_order_relaxed);
    }
    slot_raw_.assign(slot_count_, 0);
    slot_model_.assign(slot_count_, nullptr);
    slot_block_.assign(slot_count_, 0);
    free_slots_.reserve(slot_count_);
    // Hand out low slots first (free_slots_ pops from the back).
    for (std::size_t s = slot_count_; s-- > 0;) free_slots_.push_back(static_cast<std::int32_t>(s));
    for (unsigned i = 0; i < config.fetchers; ++i) fetchers_.emplace_back([this] { fetcher_loop(); });
}

BlockCache::~BlockCache() {
    {
        std::lock_guard<std::mutex> lock(mutex_);
        stop_ = true;
    }
    work_.notify_all();
    for (auto& t : fetchers_) t.join();
}

std::shared_ptr<CachedModel> BlockCache::add_model(std::shared_ptr<const ModelIndex> index) {
    std::shared_ptr<CachedModel> model;
    {
        std::lock_guard<std::mutex> lock(mutex_);
        model.reset(new CachedModel(std::move(index), next_model_id_++));
        models_.push_back(model);
    }
    // The root treelet: one block, always there, so a first frame shows voxels at once.
    preload(*model, {model->index().level_first()[0]});
    return model;
}

void BlockCache::remove_model(const std::shared_ptr<CachedModel>& model) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (model->closed_) return;
    model->closed_ = true;
    pending_.erase(std::remove_if(pending_.begin(), pending_.end(), [&](const Request& r) { return r.model == model.get(); }),
                   pending_.end());
    for (std::size_t s = 0; s < slot_count_; ++s) {
        if (slot_model_[s] != model.get()) continue;
        model->slot_of_[slot_block_[s]].store(CachedModel::kAbsent, std::memory_order_release);
        slot_model_[s] = nullptr;
        retired_.push_back({static_cast<std::int32_t>(s), tick_});
        ++evicted_total_;
    }
    // Finished but unpublished blocks were never visible: their slots are free now.
    for (auto it = ready_.begin(); it != ready_.end();) {
        if (it->model == model.get()) {
            free_slots_.push_back(it->slot);
            it = ready_.erase(it);
        } else {
            ++it;
        }
    }
    forget_if_closed_locked(*model);
    reclaim_locked();
    work_.notify_all();
}

std::size_t BlockCache::preload(CachedModel& model, const std::vector<std::uint32_t>& blocks) {
    std::size_t loaded = 0;
    std::vector<std::uint8_t> scratch;
    for (const std::uint32_t block : blocks) {
        std::int32_t slot;
        {
            std::lock_guard<std::mutex> lock(mutex_);
            if (model.closed_ || model.state_[block] != CachedModel::State::Absent) continue;
            if (free_slots_.empty()) {
                reclaim_locked();
                // Blocks stamped with the latest tick (used by the last frame, or loaded by
                // this preload) stay.
                std::uint32_t protect = tick_;
                for (const std::uint32_t t : active_ticks_) protect = std::min(protect, t);
                evict_locked(1, protect);
                reclaim_locked();
            }
            if (free_slots_.empty()) continue;
            slot = free_slots_.back();
            free_slots_.pop_back();
            model.state_[block] = CachedModel::State::Loading;
            ++model.loading_;
            ++loading_;
        }
        const std::string error =
            model.index().read_block(block, slot_bytes(slot), scratch);
        std::lock_guard<std::mutex> lock(mutex_);
        --model.loading_;
        --loading_;
        if (model.closed_) {
            free_slots_.push_back(slot);
            forget_if_closed_locked(model);
            continue;
        }
        if (!error.empty()) {
            model.state_[block] = CachedModel::State::Bad;
            model.slot_of_[block].store(CachedModel::kBad, std::memory_order_release);
            model.errors_.push_back(error);
            free_slots_.push_back(slot);
            ++failed_total_;
            continue;
        }
        // No frame uses a model before add_model returns, and preloads of an open model
        // only fill blocks no frame has seen: publishing now changes nothing under a frame.
        slot_raw_[static_cast<std::size_t>(slot)] = model.index().entry(block).raw_size;
        slot_model_[static_cast<std::size_t>(slot)] = &model;
        slot_block_[static_cast<std::size_t>(slot)] = block;
        last_used_[static_cast<std::size_t>(slot)].store(tick_, std::memory_order_relaxed);
        seen_[static_cast<std::size_t>(slot)].store(0, std::memory_order_relaxed);
        model.state_[block] = CachedModel::State::Resident;
        model.slot_of_[block].store(slot, std::memory_order_release);
        bytes_read_ += model.index().entry(block).stored_size;
        ++loaded_total_;
        ++loaded;
    }
    return loaded;
}

std::uint32_t BlockCache::begin_frame(FrameCacheStats& stats) {
    std::lock_guard<std::mutex> lock(mutex_);
    const std::uint32_t tick = ++tick_;
    stats.tick = tick;
    active_ticks_.push_back(tick);
    publish_locked(&stats);
    return tick;
}

void BlockCache::publish_locked(FrameCacheStats* stats) {
    for (const Finished& f : ready_) {
        const auto s = static_cast<std::size_t>(f.slot);
        slot_model_[s] = f.model;
        slot_block_[s] = f.block;
        // Stamped as used now, so the frame that publishes it cannot evict it unseen.
        last_used_[s].store(tick_, std::memory_order_relaxed);
        seen_[s].store(0, std::memory_order_relaxed);  // tick 0 is never a frame's
        f.model->state_[f.block] = CachedModel::State::Resident;
        f.model->slot_of_[f.block].store(f.slot, std::memory_order_release);
        ++loaded_total_;
        if (stats) ++stats->loaded;
    }
    ready_.clear();
}

namespace {

// The binary exponent of a priority (counts and projected sizes are positive): one class
// per factor of two.
int priority_class(float priority) {
    if (!(priority > 0.0f)) return std::numeric_limits<int>::min();
    int exponent = 0;
    std::frexp(priority, &exponent);
    return exponent;
}

}  // namespace

void BlockCache::end_frame(std::uint32_t tick, const std::vector<std::pair<CachedModel*, std::uint32_t>>& requests,
                           FrameCacheStats& stats, std::size_t limit) {
    Readahead readahead;
    {
        std::lock_guard<std::mutex> lock(mutex_);
        end_frame_locked(tick, requests, stats, limit, readahead);
    }
    if (readahead.empty()) return;
    // Outside the lock (the advice submits reads): runs of consecutive blocks of one
    // model become one call. The index's shared_ptr keeps its file open meanwhile.
    std::sort(readahead.begin(), readahead.end());
    std::size_t run = 0;
    for (std::size_t i = 1; i <= readahead.size(); ++i) {
        if (i < readahead.size() && readahead[i].first == readahead[run].first &&
            readahead[i].second == readahead[i - 1].second + 1) {
            continue;
        }
        readahead[run].first->read_ahead(readahead[run].second, readahead[i - 1].second);
        run = i;
    }
}

void BlockCache::end_frame_locked(std::uint32_t tick,
                                  const std::vector<std::pair<CachedModel*, std::uint32_t>>& requests,
                                  FrameCacheStats& stats, std::size_t limit, Readahead& readahead) {
    const std::size_t per_frame = limit > 0 ? std::min(limit, config_.max_pending) : config_.max_requests_per_frame;
    active_ticks_.erase(std::find(active_ticks_.begin(), active_ticks_.end(), tick));

    // Collect this frame's requests with their priorities; the atomics start again at 0.
    std::vector<Request> fresh;
    fresh.reserve(requests.size());
    for (const auto& [model, block] : requests) {
        const std::uint32_t count = model->requests_[block].exchange(0, std::memory_order_relaxed);
        const std::uint32_t size_bits = model->max_size_[block].exchange(0, std::memory_order_relaxed);
        if (model->closed_ || count == 0) continue;
        const auto state = model->state_[block];
        if (state != CachedModel::State::Absent && state != CachedModel::State::Queued) continue;
        float size;
        std::memcpy(&size, &size_bits, sizeof size);
        const float priority = config_.priority == FetchPriority::RequestCount ? static_cast<float>(count) : size;
        fresh.push_back({model, block, priority, 0});
    }
    stats.requested += requests.size();
    // The fetch list a frame may add to is bounded: the best requests go first, the rest
    // are asked again by the next frame if they still matter.
    if (fresh.size() > per_frame) {
        std::nth_element(fresh.begin(), fresh.begin() + static_cast<std::ptrdiff_t>(per_frame), fresh.end(),
                         [](const Request& a, const Request& b) { return a.priority > b.priority; });
        fresh.resize(per_frame);
    }
    for (Request& r : fresh) {
        r.serial = ++serial_;
        if (config_.readahead && r.model->state_[r.block] == CachedModel::State::Absent) {
            readahead.emplace_back(r.model->index_, r.block);
        }
        r.model->state_[r.block] = CachedModel::State::Queued;
    }
    // Merge with the queue: a block asked again keeps its newest priority.
    pending_.insert(pending_.end(), fresh.begin(), fresh.end());
    std::sort(pending_.begin(), pending_.end(), [](const Request& a, const Request& b) {
        if (a.model != b.model) return a.model->id_ < b.model->id_;
        if (a.block != b.block) return a.block < b.block;
        return a.serial > b.serial;
    });
    pending_.erase(std::unique(pending_.begin(), pending_.end(),
                               [](const Request& a, const Request& b) { return a.model == b.model && a.block == b.block; }),
                   pending_.end());
    // Requests nobody renewed for a while belong to views that moved on: keep the newest.
    if (pending_.size() > config_.max_pending) {
        std::nth_element(pending_.begin(), pending_.begin() + static_cast<std::ptrdiff_t>(config_.max_pending),
                         pending_.end(), [](const Request& a, const Request& b) { return a.serial > b.serial; });
        for (std::size_t i = config_.max_pending; i < pending_.size(); ++i) {
            pending_[i].model->state_[pending_[i].block] = CachedModel::State::Absent;
        }
        pending_.resize(config_.max_pending);
    }
    // Fetch order, best last: requests within a factor of two in priority form one
    // class, and a class is fetched in file order (ascending block ids from the back), so
    // the fetchers read forward through the file. On the disk of bench/results/complete.md
    // cold 64 KiB reads run at about 300 MB/s in file order and 80-150 MB/s in random
    // order, and a cold view's blocks are mostly of equal priority.
    if (!config_.file_order) {
        std::sort(pending_.begin(), pending_.end(), [](const Request& a, const Request& b) {
            return a.priority != b.priority ? a.priority < b.priority : a.serial < b.serial;
        });
    } else {
        std::sort(pending_.begin(), pending_.end(), [](const Request& a, const Request& b) {
            const int ca = priority_class(a.priority), cb = priority_class(b.priority);
            if (ca != cb) return ca < cb;
            if (a.model != b.model) return a.model->id_ > b.model->id_;
            return a.block > b.block;
        });
    }

    // Make room for what the fetchers can load before the next frame, evicting only
    // blocks no running frame and not this frame used.
    reclaim_locked();
    const std::size_t want = std::min(pending_.size(), per_frame);
    const std::size_t have = free_slots_.size() + retired_.size();
    if (want > have) {
        std::uint32_t protect = tick;
        for (const std::uint32_t t : active_ticks_) protect = std::min(protect, t);
        stats.evicted += evict_locked(want - have, protect);
        reclaim_locked();
    }
    stats.pending = pending_.size() + loading_ + ready_.size();
    work_.notify_all();
}

std::size_t BlockCache::evict_locked(std::size_t wanted, std::uint32_t protect_from) {
    std::vector<std::pair<std::uint32_t, std::int32_t>> candidates;
    for (std::size_t s = 0; s < slot_count_; ++s) {
        if (!slot_model_[s]) continue;
        const std::uint32_t stamp = last_used_[s].load(std::memory_order_relaxed);
        if (stamp < protect_from) candidates.emplace_back(stamp, static_cast<std::int32_t>(s));
    }
    const std::size_t n = std::min(wanted, candidates.size());
    std::partial_sort(candidates.begin(), candidates.begin() + static_cast<std::ptrdiff_t>(n), candidates.end());
    for (std::size_t i = 0; i < n; ++i) {
        const auto s = static_cast<std::size_t>(candidates[i].second);
        CachedModel* model = slot_model_[s];
        model->slot_of_[slot_block_[s]].store(CachedModel::kAbsent, std::memory_order_release);
        model->state_[slot_block_[s]] = CachedModel::State::Absent;
        slot_model_[s] = nullptr;
        retired_.push_back({candidates[i].second, tick_});
    }
    evicted_total_ += n;
    return n;
}

void BlockCache::forget_if_closed_locked(CachedModel& model) {
    // A closed model leaves the list once no fetch still writes into one of its blocks.
    if (!model.closed_ || model.loading_ > 0) return;
    models_.erase(std::remove_if(models_.begin(), models_.end(),
                                 [&](const std::shared_ptr<CachedModel>& m) { return m.get() == &model; }),
                  models_.end());
}

void BlockCache::reclaim_locked() {
    // A retired slot is free once every frame that could have looked it up has ended:
    // frames are numbered in start order, so that is every frame with tick <= retirement.
    std::uint32_t oldest = std::numeric_limits<std::uint32_t>::max();
    for (const std::uint32_t t : active_ticks_) oldest = std::min(oldest, t);
    auto it = std::partition(retired_.begin(), retired_.end(), [&](const Retired& r) { return r.tick >= oldest; });
    for (auto f = it; f != retired_.end(); ++f) free_slots_.push_back(f->slot);
    retired_.erase(it, retired_.end());
}

void BlockCache::fetcher_loop() {
    std::vector<std::uint8_t> scratch;
    std::unique_lock<std::mutex> lock(mutex_);
    for (;;) {
        work_.wait(lock, [this] { return stop_ || (!pending_.empty() && !free_slots_.empty()); });
        if (stop_) return;
        const Request r = pending_.back();
        pending_.pop_back();
        CachedModel& model = *r.model;
        if (model.closed_ || model.state_[r.block] != CachedModel::State::Queued) continue;
        const std::int32_t slot = free_slots_.back();
        free_slots_.pop_back();
        model.state_[r.block] = CachedModel::State::Loading;
        ++model.loading_;
        ++loading_;
        lock.unlock();
        const std::string error = model.index().read_block(
            r.block, slot_bytes(slot), scratch);
        lock.lock();
        --model.loading_;
        --loading_;
        ++fetch_generation_;
        if (model.closed_) {
            free_slots_.push_back(slot);
            forget_if_closed_locked(model);
        } else if (!error.empty()) {
            // Treated as missing from now on (the renderer falls back to voxels) and reported.
            model.state_[r.block] = CachedModel::State::Bad;
            model.slot_of_[r.block].store(CachedModel::kBad, std::memory_order_release);
            model.errors_.push_back(error);
            free_slots_.push_back(slot);
            ++failed_total_;
        } else {
            slot_raw_[static_cast<std::size_t>(slot)] = model.index().entry(r.block).raw_size;
            bytes_read_ += model.index().entry(r.block).stored_size;
            model.state_[r.block] = CachedModel::State::Ready;
            ready_.push_back({&model, r.block, slot});
        }
        done_.notify_all();
    }
}

bool BlockCache::wait_for_fetches(double timeout_ms) {
    std::unique_lock<std::mutex> lock(mutex_);
    if (!ready_.empty()) return true;
    if (pending_.empty() && loading_ == 0) return false;
    const std::uint64_t generation = fetch_generation_;
    return done_.wait_for(lock, std::chrono::duration<double, std::milli>(timeout_ms),
                          [&] { return fetch_generation_ != generation; });
}

void BlockCache::drain() {
    std::unique_lock<std::mutex> lock(mutex_);
    done_.wait(lock, [this] { return loading_ == 0 && (pending_.empty() || free_slots_.empty()); });
}

bool BlockCache::wait_idle(double timeout_ms) {
    std::unique_lock<std::mutex> lock(mutex_);
    return done_.wait_for(lock, std::chrono::duration<double, std::milli>(timeout_ms),
                          [this] { return loading_ == 0 && (pending_.empty() || free_slots_.empty()); });
}

CacheTotals BlockCache::totals() const {
    std::lock_guard<std::mutex> lock(mutex_);
    CacheTotals t;
    t.budget_bytes = config_.budget_bytes;
    t.slot_count = slot_count_;
    for (std::size_t s = 0; s < slot_count_; ++s) {
        if (!slot_model_[s]) continue;
        ++t.resident_blocks;
        t.resident_bytes += slot_raw_[s];
    }
    t.free_slots = free_slots_.size();
    t.retired_slots = retired_.size();
    t.pending = pending_.size();
    t.loading = loading_;
    t.ready = ready_.size();
    t.loaded = loaded_total_;
    t.evicted = evicted_total_;
    t.failed = failed_total_;
    t.bytes_read = bytes_read_;
    t.fetchers = config_.fetchers;
    t.models = models_.size();
    t.active_frames = active_ticks_.size();
    return t;
}

std::vector<std::pair<std::uint32_t, std::uint32_t>> BlockCache::resident(const CachedModel& model) const {
    std::lock_guard<std::mutex> lock(mutex_);
    std::vector<std::pair<std::uint32_t, std::uint32_t>> out;
    for (std::size_t s = 0; s < slot_count_; ++s) {
        if (slot_model_[s] == &model) out.emplace_back(slot_block_[s], last_used_[s].load(std::memory_order_relaxed));
    }
    std::sort(out.begin(), out.end());
    return out;
}

std::vector<std::string> BlockCache::model_errors(const CachedModel& model) const {
    std::lock_guard<std::mutex> lock(mutex_);
    return model.errors_;
}

std::string BlockCache::check_invariants() const {
    std::lock_guard<std::mutex> lock(mutex_);
    // Every slot is exactly one of: free, retired, loading, ready, resident.
    std::vector<int> uses(slot_count_, 0);
    for (const auto s : free_slots_) ++uses[static_cast<std::size_t>(s)];
    for (const auto& r : retired_) ++uses[static_cast<std::size_t>(r.slot)];
    for (const auto& f : ready_) ++uses[static_cast<std::size_t>(f.slot)];
    std::size_t resident = 0;
    for (std::size_t s = 0; s < slot_count_; ++s) {
        if (!slot_model_[s]) continue;
        ++uses[s];
        ++resident;
        if (slot_model_[s]->slot_of_[slot_block_[s]].load() != static_cast<std::int32_t>(s)) {
            return "slot " + std::to_string(s) + " is owned by a block whose table entry points elsewhere";
        }
    }
    std::size_t unused = 0;
    for (std::size_t s = 0; s < slot_count_; ++s) {
        if (uses[s] > 1) return "slot " + std::to_string(s) + " is in use twice";
        if (uses[s] == 0) ++unused;
    }
    if (unused != loading_) return "slots unaccounted for: " + std::to_string(unused) + " vs " + std::to_string(loading_) + " loading";
    for (const auto& m : models_) {
        for (std::size_t b = 0; b < m->index().block_count(); ++b) {
            const std::int32_t s = m->slot_of_[b].load();
            if (s >= 0 && (static_cast<std::size_t>(s) >= slot_count_ || slot_model_[static_cast<std::size_t>(s)] != m.get() ||
                           slot_block_[static_cast<std::size_t>(s)] != b)) {
                return "table entry for block " + std::to_string(b) + " points at a slot it does not own";
            }
        }
    }
    (void)resident;
    return {};
}

}  // namespace vastray
