#include "writer/parallel_emission.h"

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <exception>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <thread>
#include <unordered_map>
#include <utility>

#include "vastray/thread_pool.h"

namespace vastray::writer {

namespace {

// A subtree's leaves hold one contiguous run of the tree's triangle list (preorder), from
// its leftmost leaf to its rightmost. A node's first present child follows it directly.
std::uint64_t subtree_references(const KdTree& tree, std::uint32_t node) {
    std::uint32_t first = node, last = node;
    while (!tree.nodes[first].is_leaf()) ++first;
    while (!tree.nodes[last].is_leaf()) {
        const KdNode& k = tree.nodes[last];
        last = k.right_empty() ? last + 1 : last + k.right_offset();
    }
    const KdNode& a = tree.nodes[first];
    const KdNode& b = tree.nodes[last];
    return static_cast<std::uint64_t>(b.first()) + b.count() - a.first();
}

// The roots of the treelets one LOD level below the treelet rooted at `job.node`.
std::vector<EmissionJob> child_treelets(const KdTree& tree, const EmissionJob& job, const SubtreeEmitter& main) {
    std::vector<TreeletNode> nodes;
    collect_kd_treelet(tree, job.node, job.cell, nodes);
    std::vector<EmissionJob> out;
    for (TreeletNode& n : nodes) {
        if (n.kind != TreeletNode::Lod) continue;
        if (main.errors() != nullptr) {
            n.error = main.errors()[n.kd_node];
            main.code_error(n);
        }
        const std::uint32_t tier = main.tier_below(n);
        for (int side = 0; side < 2; ++side) {
            if ((n.empty & (side == 0 ? format::kLeftEmpty : format::kRightEmpty)) != 0) continue;
            const std::uint32_t kd = side == 0 ? n.kd_left : n.kd_right;
            out.push_back({kd, child_cell(n.cell, n.axis, n.split, side), job.level + 1, tier,
                           subtree_references(tree, kd)});
        }
    }
    return out;
}

}  // namespace

std::vector<EmissionJob> choose_jobs(const KdTree& tree, const Box3f& cell, std::size_t level, const SubtreeEmitter& main) {
    // Each job ends in a partly filled triangle block (its blocks close on their own), so
    // jobs are not made smaller than ~100 full blocks' worth of references.
    constexpr std::uint64_t kMinJob = 1 << 18;
    constexpr std::uint64_t kShare = 32;   // no job above 1/kShare of the part...
    constexpr std::size_t kMaxJobs = 512;  // ...within this many jobs
    const std::uint64_t total = subtree_references(tree, 0);
    if (total < 2 * kMinJob) return {};  // smaller parts emit on one thread
    std::vector<EmissionJob> jobs = child_treelets(tree, {0, cell, level, 0, total}, main);
    std::vector<bool> final(jobs.size(), false);  // no child treelets: cannot be split
    while (jobs.size() < kMaxJobs) {
        std::size_t biggest = jobs.size();
        for (std::size_t i = 0; i < jobs.size(); ++i) {
            if (final[i] || jobs[i].references <= std::max(total / kShare, kMinJob)) continue;
            if (biggest == jobs.size() || jobs[i].references > jobs[biggest].references) biggest = i;
        }
        if (biggest == jobs.size()) break;
        std::vector<EmissionJob> below = child_treelets(tree, jobs[biggest], main);
        if (below.empty()) {
            final[biggest] = true;
            continue;
        }
        const auto at = static_cast<std::ptrdiff_t>(biggest);
        jobs.erase(jobs.begin() + at);
        final.erase(final.begin() + at);
        jobs.insert(jobs.begin() + at, below.begin(), below.end());
        final.insert(final.begin() + at, below.size(), false);
    }
    if (jobs.size() < 2) return {};
    return jobs;
}

Pending emit_part(SubtreeEmitter& main, const KdTree& tree, const TriangleSource& src, const Box3f& cell,
                  std::size_t level, std::uint32_t tier, const ModelWriterParams& params, ProgressCounter& counter,
                  unsigned lanes) {
    const std::vector<EmissionJob> jobs = choose_jobs(tree, cell, level, main);
    if (jobs.empty()) return main.emit_kd_treelet(0, cell, level, tier);
    const std::size_t n = jobs.size();
    main.stats.emission_jobs += n;
    // Jobs buffer only their triangle blocks: their treelets go out as placement units.
    std::vector<std::vector<BufferedBlock>> buffers(n);
    std::vector<std::unique_ptr<SubtreeEmitter>> parts(n);
    std::vector<Pending> roots(n);
    std::unordered_map<std::uint32_t, std::size_t> job_of;
    for (std::size_t i = 0; i < n; ++i) {
        parts[i] = std::make_unique<SubtreeEmitter>(
            params, counter,
            [&buffers, i](int, std::uint32_t block_tier, StoredBlock&& block) {
                buffers[i].push_back({block_tier, std::move(block)});
            },
            true);
        parts[i]->bind(&tree, src, main.errors());
        job_of.emplace(jobs[i].node, i);
    }
    auto run = [&](std::size_t i) {
        roots[i] = parts[i]->emit_kd_treelet(jobs[i].node, jobs[i].cell, jobs[i].level, jobs[i].tier);
        parts[i]->finish_deferred();
    };
    auto merge = [&](std::size_t i, Pending& root) {
        main.merge(*parts[i], buffers[i], roots[i]);
        root = std::move(roots[i]);
        parts[i].reset();
        std::vector<BufferedBlock>().swap(buffers[i]);
    };

    if (lanes <= 1) {
        // One lane: each job runs when the walk reaches it, which merges the same output.
        const SubtreeEmitter::JobLookup inline_jobs = [&](std::uint32_t node, Pending& root) {
            const auto it = job_of.find(node);
            if (it == job_of.end()) return false;
            run(it->second);
            merge(it->second, root);
            return true;
        };
        return main.emit_kd_treelet(0, cell, level, tier, &inline_jobs);
    }

    std::mutex mutex;
    std::condition_variable changed;
    std::vector<char> done(n, 0);
    bool finished = false;
    std::exception_ptr failure;
    std::atomic<bool> abandon{false};
    std::thread runner([&] {
        try {
            ThreadPool::global().parallel_for(n, [&](std::size_t i, unsigned) {
                if (abandon.load(std::memory_order_relaxed)) return;
                run(i);
                {
                    std::lock_guard<std::mutex> lock(mutex);
                    done[i] = 1;
                }
                changed.notify_all();
            }, lanes);
        } catch (...) {
            std::lock_guard<std::mutex> lock(mutex);
            failure = std::current_exception();
        }
        {
            std::lock_guard<std::mutex> lock(mutex);
            finished = true;
        }
        changed.notify_all();
    });
    const SubtreeEmitter::JobLookup parallel_jobs = [&](std::uint32_t node, Pending& root) {
        const auto it = job_of.find(node);
        if (it == job_of.end()) return false;
        const std::size_t i = it->second;
        {
            std::unique_lock<std::mutex> lock(mutex);
            changed.wait(lock, [&] { return done[i] != 0 || finished; });
            if (done[i] == 0) throw std::runtime_error("an emission job failed");
        }
        merge(i, root);
        return true;
    };
    Pending result;
    try {
        result = main.emit_kd_treelet(0, cell, level, tier, &parallel_jobs);
    } catch (...) {
        abandon.store(true);
        runner.join();
        if (failure) std::rethrow_exception(failure);
        throw;
    }
    runner.join();
    if (failure) std::rethrow_exception(failure);
    return result;
}

}  // namespace vastray::writer
