// Python module vastray.native. Every heavy call releases the GIL so the server's
// event loop and other renders keep running.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cmath>
#include <cstring>
#include <memory>
#include <stdexcept>
#include <string_view>

#include "bindings_common.h"
#include "vastray/format.h"
#include "vastray/kernels.h"
#include "vastray/lz4.h"
#include "vastray/render.h"
#include "vastray/scene.h"
#include "vastray/thread_pool.h"

namespace py = pybind11;
using namespace vastray;

namespace {

using bindings::DoubleArray;
using UIntArray = py::array_t<std::uint32_t, py::array::c_style | py::array::forcecast>;
using ByteArray = py::array_t<std::uint8_t, py::array::c_style | py::array::forcecast>;

void require_shape(const py::array& a, py::ssize_t cols, const char* name) {
    if (a.ndim() != 2 || a.shape(1) != cols) {
        throw std::invalid_argument(std::string(name) + " must have shape (n, " + std::to_string(cols) + ")");
    }
}

using bindings::broadcast;
using bindings::ray_starts;
using bindings::to_numpy;
using bindings::to_vec3;

std::shared_ptr<Scene> make_scene(DoubleArray vertices, UIntArray faces, py::object colours,
                                  py::object triangle_ids, int leaf_size, float traversal_cost, float intersection_cost,
                                  float empty_space_ratio, int bins, int max_depth, unsigned threads) {
    require_shape(vertices, 3, "vertices");
    require_shape(faces, 3, "faces");
    KdBuildParams params;
    params.leaf_size = leaf_size;
    params.traversal_cost = traversal_cost;
    params.intersection_cost = intersection_cost;
    params.empty_space_ratio = empty_space_ratio;
    params.bins = bins;
    params.max_depth = max_depth;
    params.threads = threads;
    if (leaf_size < 1 || !(traversal_cost > 0) || !(intersection_cost > 0) || bins < 2 ||
        !(empty_space_ratio > 0)) {
        throw std::invalid_argument("invalid kd-tree build parameters");
    }
    ByteArray colour_array;
    const std::uint8_t* colour_ptr = nullptr;
    if (!colours.is_none()) {
        colour_array = ByteArray::ensure(colours);
        if (!colour_array) throw std::invalid_argument("colours must be a uint8 array");
        require_shape(colour_array, 3, "colours");
        if (colour_array.shape(0) != faces.shape(0)) throw std::invalid_argument("colours must have one row per face");
        colour_ptr = colour_array.data();
    }
    UIntArray id_array;
    const std::uint32_t* id_ptr = nullptr;
    if (!triangle_ids.is_none()) {
        id_array = UIntArray::ensure(triangle_ids);
        if (!id_array || id_array.ndim() != 1 || id_array.shape(0) != faces.shape(0)) {
            throw std::invalid_argument("triangle_ids must be one unsigned id per face");
        }
        id_ptr = id_array.data();
    }
    py::gil_scoped_release release;
    return std::make_shared<Scene>(vertices.data(), static_cast<std::size_t>(vertices.shape(0)), faces.data(),
                                   static_cast<std::size_t>(faces.shape(0)), colour_ptr, id_ptr, params);
}

py::dict build_stats(const Scene& s) {
    const KdTree* tree;
    {
        py::gil_scoped_release release;  // the first call builds the tree
        tree = &s.tree();
    }
    const KdBuildStats& st = tree->stats;
    py::dict d;
    d["nodes"] = st.nodes;
    d["leaves"] = st.leaves;
    d["empty_leaves"] = st.empty_leaves;
    d["references"] = st.references;
    d["degenerate"] = st.degenerate;
    d["wide_nodes"] = st.wide_nodes;
    d["max_depth"] = st.max_depth;
    d["sah_cost"] = st.sah_cost;
    d["build_ms"] = st.build_ms;
    d["memory_bytes"] = s.memory_bytes();
    const Box3f& cell = tree->bounds;  // model-local, relative to the scene's centre
    d["root_cell"] = std::make_pair(std::vector<float>{cell.lo.x, cell.lo.y, cell.lo.z},
                                    std::vector<float>{cell.hi.x, cell.hi.y, cell.hi.z});
    return d;
}

py::dict any_hit_stats(const Scene& s) {
    const WideBvh* bvh;
    {
        py::gil_scoped_release release;
        bvh = s.wide_bvh();
    }
    py::dict d;
    d["structure"] = bvh != nullptr ? "wide-bvh" : "kd-tree";
    if (bvh != nullptr) {
        d["nodes"] = bvh->nodes.size();
        d["leaves"] = bvh->leaves;
        d["max_depth"] = bvh->max_depth;
        d["build_ms"] = bvh->build_ms;
        d["memory_bytes"] = bvh->memory_bytes();
    }
    return d;
}

struct RayArrays {
    DoubleArray origins, directions;
    std::vector<double> tmin, tmax;
    std::size_t n;
};

RayArrays load_rays(DoubleArray origins, DoubleArray directions, const py::object& tmin, const py::object& tmax) {
    require_shape(origins, 3, "origins");
    require_shape(directions, 3, "directions");
    if (origins.shape(0) != directions.shape(0)) throw std::invalid_argument("origins and directions differ in length");
    const auto n = static_cast<std::size_t>(origins.shape(0));
    return {origins, directions, ray_starts(tmin, n), broadcast(tmax, n, "tmax"), n};
}

py::dict intersect(const Scene& s, DoubleArray origins, DoubleArray directions, py::object tmin,
                   py::object tmax, unsigned threads, const bindings::PlaneTuples& sections) {
    RayArrays r = load_rays(origins, directions, tmin, tmax);
    const std::vector<SectionPlane> planes = bindings::to_sections(sections);
    BatchResult res;
    {
        py::gil_scoped_release release;
        res = intersect_batch(s, r.origins.data(), r.directions.data(), r.tmin.data(), r.tmax.data(), r.n, threads,
                              planes);
    }
    const auto n = static_cast<py::ssize_t>(r.n);
    py::dict d;
    d["t"] = to_numpy(std::move(res.t), {n});
    d["prim"] = to_numpy(std::move(res.prim), {n});
    d["u"] = to_numpy(std::move(res.u), {n});
    d["v"] = to_numpy(std::move(res.v), {n});
    d["normal"] = to_numpy(std::move(res.normal), {n, 3});
    d["node_visits"] = res.counters.node_visits;
    d["triangle_tests"] = res.counters.triangle_tests;
    return d;
}

py::array_t<bool> occluded(const Scene& s, DoubleArray origins, DoubleArray directions, py::object tmin,
                           py::object tmax, unsigned threads) {
    RayArrays r = load_rays(origins, directions, tmin, tmax);
    std::vector<std::uint8_t> res;
    {
        py::gil_scoped_release release;
        res = occluded_batch(s, r.origins.data(), r.directions.data(), r.tmin.data(), r.tmax.data(), r.n, threads);
    }
    py::array_t<bool> out(static_cast<py::ssize_t>(r.n));
    auto* o = out.mutable_data();
    for (std::size_t i = 0; i < r.n; ++i) o[i] = res[i] != 0;
    return out;
}

py::tuple render_frame(const Scene& s, const Camera& camera, const RenderParams& params) {
    Frame f;
    {
        py::gil_scoped_release release;
        f = render(s, camera, params);
    }
    return bindings::frame_tuple(std::move(f));
}

using FloatArray = py::array_t<float, py::array::c_style | py::array::forcecast>;

// The indirect mode's edge-aware filter on given light and guides, through the running
// path's kernels (a test hook: the renderer filters its own buffers).
py::array_t<float> filter_light(FloatArray light, FloatArray depth, FloatArray normal, float pixel_angle,
                                unsigned threads) {
    if (depth.ndim() != 2) throw std::invalid_argument("depth must be a (height, width) array");
    const py::ssize_t h = depth.shape(0), w = depth.shape(1);
    const auto is_image = [&](const FloatArray& a) {
        return a.ndim() == 3 && a.shape(0) == h && a.shape(1) == w && a.shape(2) == 3;
    };
    if (!is_image(light) || !is_image(normal)) {
        throw std::invalid_argument("light and normal must be (height, width, 3) arrays, as depth is (height, width)");
    }
    if (!(pixel_angle > 0) || !std::isfinite(pixel_angle)) throw std::invalid_argument("pixel_angle must be > 0");
    py::array_t<float> out({h, w, py::ssize_t{3}});
    std::memcpy(out.mutable_data(), light.data(), static_cast<std::size_t>(light.size()) * sizeof(float));
    {
        py::gil_scoped_release release;
        kernels().denoise_light(out.mutable_data(), depth.data(), normal.data(), static_cast<int>(w),
                                static_cast<int>(h), pixel_angle, threads);
    }
    return out;
}

py::dict reference(DoubleArray vertices, UIntArray faces, DoubleArray origins, DoubleArray directions,
                   py::object tmin, py::object tmax, unsigned threads, bool cull) {
    require_shape(vertices, 3, "vertices");
    require_shape(faces, 3, "faces");
    RayArrays r = load_rays(origins, directions, tmin, tmax);
    ReferenceResult res;
    {
        py::gil_scoped_release release;
        res = reference_intersect(vertices.data(), static_cast<std::size_t>(vertices.shape(0)), faces.data(),
                                  static_cast<std::size_t>(faces.shape(0)), r.origins.data(), r.directions.data(),
                                  r.tmin.data(), r.tmax.data(), r.n, threads, cull);
    }
    const auto n = static_cast<py::ssize_t>(r.n);
    py::dict d;
    d["t"] = to_numpy(std::move(res.t), {n});
    d["t_second"] = to_numpy(std::move(res.t_second), {n});
    d["prim"] = to_numpy(std::move(res.prim), {n});
    d["u"] = to_numpy(std::move(res.u), {n});
    d["v"] = to_numpy(std::move(res.v), {n});
    return d;
}

py::bytes lz4_decompress(const py::bytes& data, std::size_t raw_size) {
    const std::string_view src = data;  // bytes stay alive (and unchanged) for this call
    std::string out(raw_size, '\0');
    Lz4Status status;
    {
        py::gil_scoped_release release;
        status = lz4_decompress_block(reinterpret_cast<const std::uint8_t*>(src.data()), src.size(),
                                      reinterpret_cast<std::uint8_t*>(out.data()), raw_size);
    }
    if (status != Lz4Status::Ok) throw std::invalid_argument(std::string("corrupt LZ4 block: ") + lz4_status_message(status));
    return py::bytes(out);
}

}  // namespace

void bind_model(py::module_& m);  // bindings_model.cpp
void bind_cache(py::module_& m);  // bindings_cache.cpp

PYBIND11_MODULE(native, m) {
    m.doc() = "vastray native core: kd-tree build, watertight ray tracing, tiled rendering";
    m.def("hardware_threads", &hardware_threads, "Lanes the global thread pool uses");
    bind_render_types(m);

    py::class_<Scene, std::shared_ptr<Scene>>(m, "Scene",
                                              "An in-core triangle model; the 8-wide BVH and the kd-tree its rays "
                                              "walk are built on first use")
        .def(py::init(&make_scene), py::arg("vertices"), py::arg("faces"), py::arg("colours") = py::none(),
             py::arg("triangle_ids") = py::none(), py::arg("leaf_size") = KdBuildParams{}.leaf_size,
             py::arg("traversal_cost") = KdBuildParams{}.traversal_cost,
             py::arg("intersection_cost") = KdBuildParams{}.intersection_cost,
             py::arg("empty_space_ratio") = 0.15f, py::arg("bins") = 32, py::arg("max_depth") = 0,
             py::arg("threads") = 0u)
        .def_property_readonly("triangle_count", &Scene::triangle_count)
        .def_property_readonly("has_colours", &Scene::has_colours)
        .def_property_readonly("centre", [](const Scene& s) {
            const Vec3d c = s.centre();
            return std::vector<double>{c.x, c.y, c.z};
        })
        .def_property_readonly(
            "local_vertices",
            [](const Scene& s) {
                // (triangles, 3, 3) float32 relative to the centre: what a decoded model stores.
                py::array_t<float> a({static_cast<py::ssize_t>(s.triangle_count()), py::ssize_t{3}, py::ssize_t{3}});
                std::memcpy(a.mutable_data(), s.tri_vertices(), 36 * s.triangle_count());
                return a;
            })
        .def_property_readonly("bounds", [](const Scene& s) {
            const Vec3d lo = s.world_lo(), hi = s.world_hi();
            return std::make_pair(std::vector<double>{lo.x, lo.y, lo.z}, std::vector<double>{hi.x, hi.y, hi.z});
        })
        .def_property_readonly("build_stats", &build_stats,
                               "The kd-tree's nodes, leaves, depth, SAH cost, build time and the scene's "
                               "bytes with it; builds the kd-tree if not yet built (no frame needs it "
                               "unless VASTRAY_PRIMARY=kd or VASTRAY_ANYHIT=kd)")
        .def_property_readonly("kd_tree_built", &Scene::kd_tree_built,
                               "Whether the kd-tree is built (it is built on first use)")
        .def(
            "walked_structures",
            [](const Scene& s, const std::string& shading) {
                const FrameStructures f = frame_structures(s, parse_shading(shading));
                py::dict d;
                d["wide_bvh"] = f.wide();
                d["kd_tree"] = f.kd();
                return d;
            },
            py::arg("shading"),
            "Which structures a frame of `shading` walks (wide_bvh, kd_tree: bools), by the renderer's "
            "own rule (VASTRAY_PRIMARY, VASTRAY_ANYHIT, the scene's size), without building them")
        .def("any_hit_stats", &any_hit_stats,
             "Builds the scene's 8-wide BVH, which the renderer's rays walk (primary rays unless "
             "VASTRAY_PRIMARY=kd; occluded; AO, sun and indirect shading), if not yet built; its nodes, "
             "leaves, depth, build time and bytes")
        .def("intersect", &intersect, py::arg("origins"), py::arg("directions"), py::arg("tmin") = 0.0,
             py::arg("tmax") = std::numeric_limits<double>::infinity(), py::arg("threads") = 0u,
             py::arg("sections") = bindings::PlaneTuples{},
             "Closest hits (a tmin below 0 counts as 0): dict of t (inf on a miss), prim (input "
             "triangle id, -1 on a miss), u, v "
             "barycentrics, normal (unit geometric normal); section planes (nx, ny, nz, offset) cut as "
             "in rendering")
        .def("occluded", &occluded, py::arg("origins"), py::arg("directions"), py::arg("tmin") = 0.0,
             py::arg("tmax") = std::numeric_limits<double>::infinity(), py::arg("threads") = 0u,
             "Any hit in [tmin, tmax]: bool per ray (a tmin below 0 counts as 0)")
        .def("render", &render_frame, py::arg("camera"), py::arg("params") = RenderParams{},
             "Render one frame: (image (H,W,3) uint8, depth (H,W) float32, prim (H,W) int32, FrameStats)");

    bind_model(m);
    bind_cache(m);

    // The file format's constants, for the Python writer and reader (one home: format.h).
    py::dict fmt;
    fmt["magic"] = py::bytes(reinterpret_cast<const char*>(format::kMagic), sizeof format::kMagic);
    fmt["version"] = format::kVersion;
    fmt["oldest_version"] = format::kOldestVersion;
    fmt["header_size"] = format::kHeaderSize;
    fmt["header_crc_at"] = format::kHeaderCrcAt;
    fmt["block_size"] = format::kBlockSize;
    fmt["codec_stored"] = format::kCodecStored;
    fmt["codec_lz4"] = format::kCodecLz4;
    fmt["codec_family_lz4"] = format::kCodecFamilyLz4;
    fmt["flag_colours"] = format::kFlagColours;
    fmt["flag_triangle_ids"] = format::kFlagTriangleIds;
    fmt["flag_part_ids"] = format::kFlagPartIds;
    fmt["flag_quantized_splits"] = format::kFlagQuantizedSplits;
    fmt["flag_quantized_vertices"] = format::kFlagQuantizedVertices;
    fmt["flag_tiered"] = format::kFlagTiered;
    fmt["flag_packed_treelets"] = format::kFlagPackedTreelets;
    fmt["flag_voxel_errors"] = format::kFlagVoxelErrors;
    fmt["tier_count_at"] = format::kTierCountAt;
    fmt["tier_shift"] = format::kTierShift;
    fmt["max_tiers"] = format::kMaxTiers;
    fmt["flag_compact_triangles"] = format::kFlagCompactTriangles;
    fmt["compact_header"] = format::compact::kHeader;
    fmt["compact_group"] = format::compact::kGroup;
    fmt["vertex_grid_bits"] = format::kVertexGridBits;
    fmt["split_bits"] = format::kSplitBits;
    fmt["level_record"] = format::kLevelRecord;
    fmt["entry_record"] = format::kEntryRecord;
    fmt["parts_offset_at"] = format::kPartsOffsetAt;
    fmt["parts_head"] = format::kPartsHead;
    fmt["part_record"] = format::kPartRecord;
    fmt["run_record"] = format::kRunRecord;
    fmt["no_part"] = format::kNoPart;
    m.attr("FORMAT") = fmt;

    m.def(
        "voxel_face_sample",
        [](const py::bytes& voxel, int face) {
            const std::string_view v(voxel);
            if (face < 0 || face > 5) throw std::invalid_argument("face must be 0 ... 5");
            std::uint32_t first = 0;
            if (v.size() >= 4) std::memcpy(&first, v.data(), 4);
            if (v.size() < 4 * static_cast<std::size_t>(format::voxel_words(first))) {
                throw std::invalid_argument("the voxel's words are cut short");
            }
            return format::voxel_face_sample(reinterpret_cast<const std::uint8_t*>(v.data()), face);
        },
        py::arg("voxel"), py::arg("face"),
        "The sample face `face` of a voxel shows, as the renderer reads it (its stored words from the first; test hook)");

    m.def("lz4_decompress", &lz4_decompress, py::arg("data"), py::arg("raw_size"),
          "Decode one LZ4 block (block format, no frame) of exactly raw_size bytes; ValueError if corrupt");

    m.def("reference_intersect", &reference, py::arg("vertices"), py::arg("faces"), py::arg("origins"),
          py::arg("directions"), py::arg("tmin") = 0.0, py::arg("tmax") = std::numeric_limits<double>::infinity(),
          py::arg("threads") = 0u, py::arg("cull") = true,
          "Brute-force double-precision closest hits (test reference): t, t_second, prim, u, v");
    m.def("denoise_light", &filter_light, py::arg("light"), py::arg("depth"), py::arg("normal"),
          py::arg("pixel_angle"), py::arg("threads") = 0u,
          "The indirect mode's edge-aware filter (test hook): light (h, w, 3) filtered under the guides "
          "depth (h, w; inf where nothing was hit) and unit normals (h, w, 3)");
}
