// Helpers shared by the binding files of vastray.native: numpy hand-over, vector
// arguments, and the camera and frame conversions every render call uses.
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <stdexcept>
#include <string>
#include <vector>

#include "vastray/render.h"

namespace vastray::bindings {

namespace py = pybind11;

inline Vec3d to_vec3(const std::vector<double>& v, const char* name) {
    if (v.size() != 3) throw std::invalid_argument(std::string(name) + " must have three components");
    return {v[0], v[1], v[2]};
}

// Hands a vector to numpy without a copy; the capsule frees it with the array.
template <typename T>
py::array_t<T> to_numpy(std::vector<T>&& v, std::vector<py::ssize_t> shape) {
    auto* heap = new std::vector<T>(std::move(v));
    py::capsule owner(heap, [](void* p) { delete static_cast<std::vector<T>*>(p); });
    return py::array_t<T>(shape, heap->data(), owner);
}

struct RenderArgs {
    Camera camera;
    RenderParams params;
};

inline RenderArgs render_args(const std::vector<double>& eye, const std::vector<double>& target,
                              const std::vector<double>& up, double fov, int width, int height,
                              const std::string& shading, int ao_samples, double ao_distance,
                              const std::vector<double>& sun, unsigned threads, int tile_size, int packets) {
    RenderArgs a;
    a.camera.eye = to_vec3(eye, "eye");
    a.camera.target = to_vec3(target, "target");
    a.camera.up = to_vec3(up, "up");
    a.camera.fov_deg = fov;
    a.camera.width = width;
    a.camera.height = height;
    a.params.shading = parse_shading(shading);
    a.params.ao_samples = ao_samples;
    a.params.ao_distance = ao_distance;
    a.params.sun_direction = to_vec3(sun, "sun");
    a.params.threads = threads;
    a.params.tile_size = tile_size;
    if (packets != 1 && packets != 4 && packets != 16) throw std::invalid_argument("packets must be 1, 4 or 16");
    a.params.packets = packets;
    return a;
}

// image, depth, prim and the ray statistics of a frame, as a dict.
inline py::dict frame_dict(Frame&& f) {
    const py::ssize_t h = f.height, w = f.width;
    py::dict d;
    d["image"] = to_numpy(std::move(f.rgb), {h, w, 3});
    d["depth"] = to_numpy(std::move(f.depth), {h, w});
    d["prim"] = to_numpy(std::move(f.prim), {h, w});
    py::dict st;
    st["primary_rays"] = f.stats.primary_rays;
    st["secondary_rays"] = f.stats.secondary_rays;
    st["rays"] = f.stats.primary_rays + f.stats.secondary_rays;
    st["node_visits"] = f.stats.node_visits;
    st["triangle_tests"] = f.stats.triangle_tests;
    st["milliseconds"] = f.stats.milliseconds;
    st["threads"] = f.stats.threads;
    d["stats"] = st;
    return d;
}

}  // namespace vastray::bindings
