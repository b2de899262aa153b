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

using bindings::broadcast;
using bindings::DoubleArray;

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

    py::tuple render(const Camera& camera, const RenderParams& params) {
        CachedModel& m = model();
        Frame f;
        {
            py::gil_scoped_release release;
            f = render_lod(*cache_, m, camera, params);
        }
        return bindings::frame_tuple(std::move(f));
    }

    py::dict intersect(DoubleArray origins, DoubleArray directions, const py::object& tmin, const py::object& tmax,
                       unsigned threads, const bindings::PlaneTuples& sections) {
        const std::vector<SectionPlane> planes = bindings::to_sections(sections);
        if (origins.ndim() != 2 || origins.shape(1) != 3 || directions.ndim() != 2 || directions.shape(1) != 3 ||
            origins.shape(0) != directions.shape(0)) {
            throw std::invalid_argument("origins and directions must both have shape (n, 3)");
        }
        const auto n = static_cast<std::size_t>(origins.shape(0));
        const std::vector<double> lo = bindings::ray_starts(tmin, n), hi = broadcast(tmax, n, "tmax");
        CachedModel& m = model();
        LodRayHits r;
        {
            py::gil_scoped_release release;
            r = intersect_lod(*cache_, m, origins.data(), directions.data(), lo.data(), hi.data(), n, threads, planes);
        }
        const auto rows = static_cast<py::ssize_t>(n);
        py::dict d;
        d["t"] = bindings::to_numpy(std::move(r.t), {rows});
        d["position"] = bindings::to_numpy(std::move(r.position), {rows, 3});
        d["normal"] = bindings::to_numpy(std::move(r.normal), {rows, 3});
        d["prim"] = bindings::to_numpy(std::move(r.prim), {rows});
        d["u"] = bindings::to_numpy(std::move(r.u), {rows});
        d["v"] = bindings::to_numpy(std::move(r.v), {rows});
        d["complete"] = bindings::to_numpy(std::move(r.complete), {rows}).attr("astype")("bool");
        d["stats"] = r.stats;
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
                                       std::size_t max_requests_per_frame, std::size_t max_pending,
                                       bool file_order, bool huge_pages, bool readahead) {
    CacheConfig c;
    c.budget_bytes = budget;
    c.fetchers = fetchers;
    if (priority == "count") c.priority = FetchPriority::RequestCount;
    else if (priority == "size") c.priority = FetchPriority::ProjectedSize;
    else throw std::invalid_argument("priority must be 'count' (paper 000) or 'size' (paper 003)");
    c.max_requests_per_frame = max_requests_per_frame;
    c.max_pending = max_pending;
    c.file_order = file_order;
    c.huge_pages = huge_pages;
    c.readahead = readahead;
    return std::make_shared<BlockCache>(c);
}

}  // namespace

void bind_cache(py::module_& m) {
    py::class_<BlockCache, std::shared_ptr<BlockCache>>(m, "BlockCache",
                                                        "Shared 64 KB block cache with fetcher threads")
        .def(py::init(&make_cache), py::arg("budget"), py::arg("fetchers") = 2u, py::arg("priority") = "count",
             py::arg("max_requests_per_frame") = 256, py::arg("max_pending") = 4096, py::arg("file_order") = true,
             py::arg("huge_pages") = true, py::arg("readahead") = true)
        .def("totals", [](const BlockCache& c) { return totals_dict(c.totals()); })
        .def("check_invariants", &BlockCache::check_invariants)
        .def("drain", &BlockCache::drain, py::call_guard<py::gil_scoped_release>(),
             "Wait until nothing is queued or loading (or no slot is free)")
        .def("wait_idle", &BlockCache::wait_idle, py::arg("timeout_ms"), py::call_guard<py::gil_scoped_release>(),
             "Wait until nothing is queued or loading (or no slot is free); False on timeout")
        .def("wait_for_fetches", &BlockCache::wait_for_fetches, py::arg("timeout_ms"),
             py::call_guard<py::gil_scoped_release>(), "Wait for a fetch to finish; False on timeout or if none pending")
        .def_property_readonly("slot_count", &BlockCache::slot_count)
        .def_property_readonly("huge_pages", &BlockCache::huge_pages,
                               "Whether the kernel took the advice to back the slots with 2 MiB pages")
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
        .def("render", &PyCachedModel::render, py::arg("camera"), py::arg("params") = RenderParams{},
             "Render one frame from the cache; never waits for data (stats say what was missing): "
             "(image, depth, prim, FrameStats)")
        .def("intersect", &PyCachedModel::intersect, py::arg("origins"), py::arg("directions"), py::arg("tmin") = 0.0,
             py::arg("tmax") = std::numeric_limits<double>::infinity(), py::arg("threads") = 0u,
             py::arg("sections") = bindings::PlaneTuples{},
             "Full-detail closest hits of world rays from what is cached; never waits. dict of t (world "
             "distance), position, normal, prim (input triangle id, -1 on a miss), u, v, complete (False: "
             "a block it needs was requested; ask again), stats")
        .def("close", &PyCachedModel::close);
}
