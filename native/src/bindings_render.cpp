// Python classes of what every render takes and gives: Camera, RenderParams and
// FrameStats (part of vastray.native). Bound once, used by both renderers, so the
// Python API, the CLI and the server's schemas share one set of names and defaults.
#include <pybind11/operators.h>

#include <sstream>

#include "bindings_common.h"
#include "vastray/isa.h"

namespace py = pybind11;

namespace vastray {

namespace {

std::vector<double> to_list(const Vec3d& v) { return {v.x, v.y, v.z}; }

// Fields of FrameStats as (name, getter): one table for the attributes and as_dict().
using StatGetter = py::object (*)(const FrameStats&);
#define VASTRAY_STAT(name, expr) {name, [](const FrameStats& s) -> py::object { return py::cast(expr); }}
const std::vector<std::pair<const char*, StatGetter>>& stat_fields() {
    static const std::vector<std::pair<const char*, StatGetter>> fields = {
        VASTRAY_STAT("primary_rays", s.primary_rays),
        VASTRAY_STAT("secondary_rays", s.secondary_rays),
        VASTRAY_STAT("rays", s.primary_rays + s.secondary_rays),
        VASTRAY_STAT("node_visits", s.node_visits),
        VASTRAY_STAT("triangle_tests", s.triangle_tests),
        VASTRAY_STAT("voxel_hits", s.voxel_hits),
        VASTRAY_STAT("milliseconds", s.milliseconds),
        VASTRAY_STAT("threads", s.threads),
        VASTRAY_STAT("complete", s.complete),
        VASTRAY_STAT("tick", s.cache.tick),
        VASTRAY_STAT("blocks_requested", s.cache.requested),
        VASTRAY_STAT("blocks_loaded", s.cache.loaded),
        VASTRAY_STAT("blocks_evicted", s.cache.evicted),
        VASTRAY_STAT("pending", s.cache.pending),
        VASTRAY_STAT("lookups", s.cache.lookups),
        VASTRAY_STAT("cache_hit_rate", s.cache.lookups ? static_cast<double>(s.cache.lookup_hits) /
                                                             static_cast<double>(s.cache.lookups)
                                                       : 1.0),
        VASTRAY_STAT("working_set_blocks", s.cache.working_set_blocks),
        VASTRAY_STAT("working_set_bytes", s.cache.working_set_bytes),
        VASTRAY_STAT("bad_blocks", s.cache.bad_blocks),
    };
    return fields;
}
#undef VASTRAY_STAT

}  // namespace

void bind_render_types(py::module_& m) {
    m.def("isa", [] { return std::string(isa_name(active_isa())); },
          "The instruction-set path the kernels run on (sse2, avx, avx2): VASTRAY_ISA if set, else the "
          "best this CPU supports");
    m.def("supported_isas", [] {
        std::vector<std::string> out;
        for (const Isa isa : supported_isas()) out.emplace_back(isa_name(isa));
        return out;
    }, "The instruction-set paths this build and CPU can run, slowest first (values for VASTRAY_ISA)");
    m.attr("MAX_IMAGE_SIDE") = kMaxImageSide;
    // Both tuples from the one list of modes, named as parse_shading reads them.
    py::list modes, any_hit;
    for (const Shading s : {Shading::Normal, Shading::Headlight, Shading::Sun, Shading::AmbientOcclusion,
                            Shading::Indirect}) {
        modes.append(shading_name(s));
        if (traces_any_hit_rays(s)) any_hit.append(shading_name(s));
    }
    m.attr("SHADING_MODES") = py::tuple(modes);
    m.attr("ANY_HIT_SHADINGS") = py::tuple(any_hit);

    py::class_<Camera>(m, "Camera", "Pinhole (or orthographic) camera in world coordinates (double precision)")
        .def(py::init([](const std::vector<double>& eye, const std::vector<double>& target,
                         const std::vector<double>& up, double fov, int width, int height, bool orthographic) {
                 Camera c;
                 c.eye = bindings::to_vec3(eye, "eye");
                 c.target = bindings::to_vec3(target, "target");
                 c.up = bindings::to_vec3(up, "up");
                 c.fov_deg = fov;
                 c.width = width;
                 c.height = height;
                 c.orthographic = orthographic;
                 return c;
             }),
             py::arg("eye"), py::arg("target"), py::arg("up") = std::vector<double>{0, 1, 0}, py::arg("fov") = 45.0,
             py::arg("width") = 640, py::arg("height") = 480, py::arg("orthographic") = false)
        .def_property_readonly("eye", [](const Camera& c) { return to_list(c.eye); })
        .def_property_readonly("target", [](const Camera& c) { return to_list(c.target); })
        .def_property_readonly("up", [](const Camera& c) { return to_list(c.up); })
        .def_readonly("fov", &Camera::fov_deg)
        .def_readonly("width", &Camera::width)
        .def_readonly("height", &Camera::height)
        .def_readonly("orthographic", &Camera::orthographic)
        .def("validate", &Camera::validate, "ValueError with the reason for absurd values");

    py::class_<RenderParams>(m, "RenderParams",
                             "How a frame is rendered: shading, ray packets, threads, level of detail")
        .def(py::init<>())
        .def_property(
            "shading", [](const RenderParams& p) { return std::string(shading_name(p.shading)); },
            [](RenderParams& p, const std::string& name) { p.shading = parse_shading(name); },
            "normal, headlight, sun (shadow rays), ao (ambient occlusion) or indirect (sun, shadows, one "
            "bounce and a sky, denoised)")
        .def_readwrite("ao_samples", &RenderParams::ao_samples, "AO rays per pixel, 1..1024")
        .def_readwrite("ao_distance", &RenderParams::ao_distance, "AO ray length; 0: a fifth of the model diagonal")
        .def_property(
            "sun_direction", [](const RenderParams& p) { return to_list(p.sun_direction); },
            [](RenderParams& p, const std::vector<double>& v) { p.sun_direction = bindings::to_vec3(v, "sun_direction"); },
            "direction towards the sun (world frame)")
        .def_property(
            "threads", [](const RenderParams& p) { return static_cast<int>(p.threads); },
            [](RenderParams& p, int n) {
                if (n < 0) throw std::invalid_argument("threads must be >= 0 (0: all cores)");
                p.threads = static_cast<unsigned>(n);
            },
            "render threads; 0: every lane of the pool")
        .def_readwrite("tile_size", &RenderParams::tile_size, "tile side in pixels, 4..1024")
        .def_readwrite("packets", &RenderParams::packets,
                       "primary rays per packet: 16, 4, 1, or 0 for the renderer's fastest")
        .def_readwrite("pixels_of_error", &RenderParams::pixels_of_error,
                       "LOD accuracy: a voxel may stand in once it is at most this many pixels wide; 0: full detail")
        .def_readwrite("solid_angle", &RenderParams::solid_angle,
                       "AO and diffuse-ray LOD metric in steradians; negative: derived from pixels_of_error")
        .def_readwrite("sample_index", &RenderParams::sample_index,
                       "pass of a still view: pass k draws other AO and diffuse directions than passes before it")
        .def_readwrite("request_limit", &RenderParams::request_limit,
                       "out of core: blocks this frame may add to the fetch queue; 0: the cache's bound")
        .def_property(
            "sections", [](const RenderParams& p) { return bindings::from_sections(p.sections); },
            [](RenderParams& p, const bindings::PlaneTuples& planes) { p.sections = bindings::to_sections(planes); },
            "section planes as (nx, ny, nz, offset): geometry where n . p + offset < 0 is cut away")
        .def_property(
            "highlight", [](const RenderParams& p) { return bindings::from_ranges(p.highlight); },
            [](RenderParams& p, const py::object& ranges) { p.highlight = bindings::to_ranges(ranges); },
            "highlighted triangles: sorted, disjoint runs [first, end) of input triangle ids, as an "
            "(N, 2) integer array or a list of pairs")
        .def("validate", &RenderParams::validate, "ValueError naming the field and its range")
        .def("__copy__", [](const RenderParams& p) { return p; })
        .def(py::pickle([](const RenderParams& p) {
                            return py::make_tuple(std::string(shading_name(p.shading)), p.ao_samples, p.ao_distance,
                                                  to_list(p.sun_direction), p.threads, p.tile_size, p.packets,
                                                  p.pixels_of_error, p.solid_angle, p.sample_index, p.request_limit,
                                                  bindings::from_sections(p.sections), bindings::from_ranges(p.highlight));
                        },
                        [](const py::tuple& t) {
                            RenderParams p;
                            p.shading = parse_shading(t[0].cast<std::string>());
                            p.ao_samples = t[1].cast<int>();
                            p.ao_distance = t[2].cast<double>();
                            p.sun_direction = bindings::to_vec3(t[3].cast<std::vector<double>>(), "sun_direction");
                            p.threads = t[4].cast<unsigned>();
                            p.tile_size = t[5].cast<int>();
                            p.packets = t[6].cast<int>();
                            p.pixels_of_error = t[7].cast<double>();
                            p.solid_angle = t[8].cast<double>();
                            p.sample_index = t[9].cast<int>();
                            p.request_limit = t[10].cast<int>();
                            p.sections = bindings::to_sections(t[11].cast<bindings::PlaneTuples>());
                            if (t.size() > 12) p.highlight = bindings::to_ranges(t[12]);
                            return p;
                        }));

    auto stats = py::class_<FrameStats>(m, "FrameStats", "What one frame or ray batch reports");
    stats.def(py::init<>());
    for (const auto& [name, getter] : stat_fields()) {
        stats.def_property_readonly(name, [get = getter](const FrameStats& s) { return get(s); });
    }
    stats.def_property_readonly_static("fields", [](const py::object&) {
        py::list names;
        for (const auto& field : stat_fields()) names.append(field.first);
        return py::tuple(names);
    });
    stats.def("as_dict", [](const FrameStats& s) {
        py::dict d;
        for (const auto& [name, getter] : stat_fields()) d[name] = getter(s);
        return d;
    });
    stats.def("__repr__", [](const FrameStats& s) {
        std::ostringstream out;
        out << "FrameStats(" << s.primary_rays + s.secondary_rays << " rays, " << s.milliseconds << " ms, "
            << (s.complete ? "complete" : "incomplete") << ")";
        return out.str();
    });
}

}  // namespace vastray
