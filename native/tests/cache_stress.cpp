// Stress test of the block cache and the LOD renderer under concurrency, meant for a
// ThreadSanitizer build (cmake -DVASTRAY_TSAN=ON -DVASTRAY_NATIVE_TESTS=ON; `make tsan`).
//
// Several threads render frames of two models (one file opened twice counts as two) in
// one small cache, with cameras that orbit so blocks keep being requested, loaded,
// published and evicted while other frames run. Exits non-zero if an invariant breaks
// or a render throws; ThreadSanitizer reports (and fails on) any data race.
#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "vastray/block_cache.h"
#include "vastray/lod_render.h"

using namespace vastray;

int main(int argc, char** argv) {
    if (argc < 2) {
        std::fprintf(stderr, "usage: %s MODEL.vast [MODEL2.vast] [frames-per-thread]\n", argv[0]);
        return 2;
    }
    const std::string path_a = argv[1];
    const std::string path_b = argc > 2 ? argv[2] : argv[1];
    const int frames = argc > 3 ? std::atoi(argv[3]) : 12;

    CacheConfig config;
    config.budget_bytes = 24 * BlockCache::kSlotBytes;  // small: evictions all the time
    config.fetchers = 3;
    config.max_requests_per_frame = 16;
    config.max_pending = 64;
    BlockCache cache(config);
    std::vector<std::shared_ptr<CachedModel>> models = {
        cache.add_model(std::make_shared<const ModelIndex>(path_a)),
        cache.add_model(std::make_shared<const ModelIndex>(path_b)),
    };

    std::atomic<int> failures{0};
    std::atomic<std::uint64_t> voxel_hits{0}, loaded{0}, evicted{0};
    std::vector<std::thread> threads;
    for (int t = 0; t < 4; ++t) {
        threads.emplace_back([&, t] {
            CachedModel& model = *models[static_cast<std::size_t>(t % 2)];
            const ModelIndex& index = model.index();
            const Box3f& cell = index.root_cell();
            const Vec3d centre = index.centre() + Vec3d((cell.lo + cell.hi) * 0.5f);
            const double radius = 1.5 * length(Vec3d(cell.hi - cell.lo));
            for (int f = 0; f < frames; ++f) {
                const double angle = 0.7 * f + 1.3 * t;
                Camera cam;
                cam.eye = centre + Vec3d(std::cos(angle), 0.4, std::sin(angle)) * radius * (0.4 + 0.1 * (f % 5));
                cam.target = centre;
                cam.width = 48;
                cam.height = 32;
                RenderParams params;
                params.shading = f % 3 == 0 ? Shading::Sun : (f % 3 == 1 ? Shading::Headlight : Shading::AmbientOcclusion);
                params.ao_samples = 2;
                params.pixels_of_error = (f % 4) * 1.5;
                try {
                    const Frame frame = render_lod(cache, model, cam, params);
                    voxel_hits += frame.stats.voxel_hits;
                    loaded += frame.stats.cache.loaded;
                    evicted += frame.stats.cache.evicted;
                } catch (const std::exception& e) {
                    std::fprintf(stderr, "render failed: %s\n", e.what());
                    ++failures;
                }
                const std::string broken = cache.check_invariants();
                if (!broken.empty()) {
                    std::fprintf(stderr, "invariant broken: %s\n", broken.c_str());
                    ++failures;
                }
                cache.wait_for_fetches(2.0);
            }
        });
    }
    for (auto& th : threads) th.join();
    cache.drain();
    const CacheTotals totals = cache.totals();
    std::printf("frames %d x 4 threads, blocks loaded %llu, evicted %llu, voxel hits %llu, resident %zu of %zu slots\n",
                frames, static_cast<unsigned long long>(loaded.load()), static_cast<unsigned long long>(evicted.load()),
                static_cast<unsigned long long>(voxel_hits.load()), totals.resident_blocks, totals.slot_count);
    if (totals.resident_bytes > config.budget_bytes) {
        std::fprintf(stderr, "resident bytes %zu exceed the budget\n", totals.resident_bytes);
        ++failures;
    }
    if (evicted.load() == 0) {
        std::fprintf(stderr, "no evictions: the stress test did not stress the cache\n");
        ++failures;
    }
    cache.remove_model(models[0]);
    cache.remove_model(models[1]);
    return failures.load() == 0 ? 0 : 1;
}
