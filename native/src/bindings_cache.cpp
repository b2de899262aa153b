// Python bindings of the block cache and the LOD renderer (part of vastray.native).
#include <memory>
#include <stdexcept>
#include <string>

#include "bindings_common.h"
#include "vastray/block_cache.h"
#include "vastray/lod_render.h"

namespace py = pybind11;
using namespace vastray;

namespace {

// A model opened in a cache. Holding the cache keeps it (and its fetchers) alive for as
// long as any of its models is.
class PyCachedModel {
public:
    PyCachedModel(std::shared_ptr<BlockCache> cache, const std::string& path) : cache_(std::move(cache)) {
        std::shared_ptr<const ModelIndex> index;
        {
            py::gil_scoped_release release;
            index = std::make_shared<const ModelIndex>(path);
            model_ = cache_->add_model(index);
        }
    }
    ~PyCachedModel() { close(); }

    void close() {
        if (!model_) return;
        cache_->remove_model(model_);
        model_.reset();
    }

    CachedModel& model() const {
        if (!model_) throw std::runtime_error("model is closed");
        return *model_;
    }
    const ModelIndex& index() const { return model().index(); }
    const BlockCache& cache() const { return *cache_; }

    std::size_t preload_levels(std::size_t levels) {
        const auto& first = index().level_first();
        std::vector<std::uint32_t> blocks;
        const std::size_t node_levels = index().level_count() - 1;
        for (std::size_t l = 0; l < std::min(levels, node_levels); ++l) {
            for (std::uint32_t b = first[l]; b < first[l + 1]; ++b) blocks.push_back(b);
        }
        py::gil_scoped_release release;
        return cache_->preload(model(), blocks);
    }

    py::dict render(const std::vector<double>& eye, const std::vector<double>& target, const std::vector<double>& up,
                    double fov, int width, int height, const std::string& shading, int ao_samples,
                    double ao_distance, const std::vector<double>& sun, unsigned threads, int tile_size,
                    double pixels_of_error, double solid_angle, int packets) {
        if (packets != 1 && packets != 4 && packets != 16) throw std::invalid_argument("packets must be 1, 4 or 16");
        const bindings::RenderArgs a = bindings::render_args(eye, target, up, fov, width, height, shading, ao_samples,
                                                             ao_distance, sun, threads, tile_size, packets);
        LodParams lod;
        lod.pixels_of_error = pixels_of_error;
        lod.solid_angle = solid_angle;
        CachedModel& m = model();
        LodFrame f;
        {
            py::gil_scoped_release release;
            f = render_lod(*cache_, m, a.camera, a.params, lod);
        }
        py::dict d = bindings::frame_dict(std::move(f.frame));
        py::dict st = d["stats"];
        st["voxel_hits"] = f.voxel_hits;
        st["blocks_requested"] = f.cache.requested;
        st["blocks_loaded"] = f.cache.loaded;
        st["blocks_evicted"] = f.cache.evicted;
        st["pending"] = f.cache.pending;
        st["lookups"] = f.cache.lookups;
        st["cache_hit_rate"] = f.cache.lookups ? static_cast<double>(f.cache.lookup_hits) / static_cast<double>(f.cache.lookups) : 1.0;
        st["working_set_blocks"] = f.cache.working_set_blocks;
        st["working_set_bytes"] = f.cache.working_set_bytes;
        st["bad_blocks"] = f.cache.bad_blocks;
        st["complete"] = f.complete;
        st["tick"] = f.cache.tick;
        d["complete"] = f.complete;
        return d;
    }

private:
    std::shared_ptr<BlockCache> cache_;
    std::shared_ptr<CachedModel> model_;
};

py::dict totals_dict(const CacheTotals& t) {
    py::dict d;
    d["budget_bytes"] = t.budget_bytes;
    d["slot_count"] = t.slot_count;
    d["resident_blocks"] = t.resident_blocks;
    d["resident_bytes"] = t.resident_bytes;
    d["free_slots"] = t.free_slots;
    d["retired_slots"] = t.retired_slots;
    d["pending"] = t.pending;
    d["loading"] = t.loading;
    d["ready"] = t.ready;
    d["loaded"] = t.loaded;
    d["evicted"] = t.evicted;
    d["failed"] = t.failed;
    d["bytes_read"] = t.bytes_read;
    d["fetchers"] = t.fetchers;
    d["models"] = t.models;
    d["active_frames"] = t.active_frames;
    return d;
}

std::shared_ptr<BlockCache> make_cache(std::size_t budget, unsigned fetchers, const std::string& priority,
                                       std::size_t max_requests_per_frame, std::size_t max_pending) {
    CacheConfig c;
    c.budget_bytes = budget;
    c.fetchers = fetchers;
    if (priority == "count") c.priority = FetchPriority::RequestCount;
    else if (priority == "size") c.priority = FetchPriority::ProjectedSize;
    else throw std::invalid_argument("priority must be 'count' (paper 000) or 'size' (paper 003)");
    c.max_requests_per_frame = max_requests_per_frame;
    c.max_pending = max_pending;
    return std::make_shared<BlockCache>(c);
}

}  // namespace

void bind_cache(py::module_& m) {
    py::class_<BlockCache, std::shared_ptr<BlockCache>>(m, "BlockCache",
                                                        "Shared 64 KB block cache with fetcher threads")
        .def(py::init(&make_cache), py::arg("budget"), py::arg("fetchers") = 2u, py::arg("priority") = "count",
             py::arg("max_requests_per_frame") = 256, py::arg("max_pending") = 4096)
        .def("totals", [](const BlockCache& c) { return totals_dict(c.totals()); })
        .def("check_invariants", &BlockCache::check_invariants)
        .def("drain", &BlockCache::drain, py::call_guard<py::gil_scoped_release>(),
             "Wait until nothing is queued or loading (or no slot is free)")
        .def("wait_for_fetches", &BlockCache::wait_for_fetches, py::arg("timeout_ms"),
             py::call_guard<py::gil_scoped_release>(), "Wait for a fetch to finish; False on timeout or if none pending")
        .def_property_readonly("slot_count", &BlockCache::slot_count)
        .def("open", [](const std::shared_ptr<BlockCache>& c, const std::string& path) {
            return std::make_unique<PyCachedModel>(c, path);
        }, py::arg("path"), "Open a built model in this cache (its root treelet is loaded at once)");

    py::class_<PyCachedModel>(m, "CachedModel", "A built model rendered through a block cache")
        .def_property_readonly("path", [](const PyCachedModel& p) { return p.index().path(); })
        .def_property_readonly("block_count", [](const PyCachedModel& p) { return p.index().block_count(); })
        .def_property_readonly("level_first", [](const PyCachedModel& p) { return p.index().level_first(); })
        .def_property_readonly("triangle_count", [](const PyCachedModel& p) { return p.index().triangle_count(); })
        .def_property_readonly("input_triangles", [](const PyCachedModel& p) { return p.index().input_triangles(); })
        .def_property_readonly("has_colours", [](const PyCachedModel& p) { return p.index().has_colours(); })
        .def_property_readonly("file_size", [](const PyCachedModel& p) { return p.index().file_size(); })
        .def_property_readonly("centre", [](const PyCachedModel& p) {
            const Vec3d c = p.index().centre();
            return std::vector<double>{c.x, c.y, c.z};
        })
        .def_property_readonly("bounds", [](const PyCachedModel& p) {
            const Vec3d c = p.index().centre();
            const Box3f& b = p.index().root_cell();
            const Vec3d lo = c + Vec3d(b.lo), hi = c + Vec3d(b.hi);
            return std::make_pair(std::vector<double>{lo.x, lo.y, lo.z}, std::vector<double>{hi.x, hi.y, hi.z});
        })
        .def_property_readonly("errors", [](const PyCachedModel& p) {
            return p.cache().model_errors(p.model());
        })
        .def("resident", [](const PyCachedModel& p) { return p.cache().resident(p.model()); },
             "Resident blocks as (global block id, tick of the last frame that used it)")
        .def("preload_levels", &PyCachedModel::preload_levels, py::arg("levels"),
             "Load the first `levels` node levels now (as far as free slots allow)")
        .def("render", &PyCachedModel::render, py::arg("eye"), py::arg("target"), py::arg("up"), py::arg("fov"),
             py::arg("width"), py::arg("height"), py::arg("shading") = "headlight", py::arg("ao_samples") = 8,
             py::arg("ao_distance") = 0.0, py::arg("sun") = std::vector<double>{0.35, 0.8, 0.5},
             py::arg("threads") = 0u, py::arg("tile_size") = 16, py::arg("pixels_of_error") = 2.0,
             py::arg("solid_angle") = -1.0, py::arg("packets") = 1,
             "Render one frame from the cache; never waits for data (stats say what was missing)")
        .def("close", &PyCachedModel::close);
}
