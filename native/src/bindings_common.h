// Helpers shared by the binding files of vastray.native: numpy hand-over, vector
// arguments, and the frame conversion every render call uses.
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <array>
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

using DoubleArray = py::array_t<double, py::array::c_style | py::array::forcecast>;

// tmin/tmax of ray queries: a scalar or one value per ray.
inline std::vector<double> broadcast(const py::object& value, std::size_t n, const char* name) {
    auto arr = DoubleArray::ensure(value);
    if (!arr) throw std::invalid_argument(std::string(name) + " must be a number or an array");
    if (arr.ndim() == 0 || arr.size() == 1) return std::vector<double>(n, *arr.data());
    if (static_cast<std::size_t>(arr.size()) != n) {
        throw std::invalid_argument(std::string(name) + " must be a scalar or have one value per ray");
    }
    return std::vector<double>(arr.data(), arr.data() + n);
}

// Section planes as Python gives them: (nx, ny, nz, offset) each.
using PlaneTuples = std::vector<std::array<double, 4>>;
inline std::vector<SectionPlane> to_sections(const PlaneTuples& planes) {
    std::vector<SectionPlane> out;
    for (const auto& p : planes) out.push_back({{p[0], p[1], p[2]}, p[3]});
    return out;
}
inline PlaneTuples from_sections(const std::vector<SectionPlane>& planes) {
    PlaneTuples out;
    for (const auto& p : planes) out.push_back({p.normal.x, p.normal.y, p.normal.z, p.offset});
    return out;
}

// Hands a vector to numpy without a copy; the capsule frees it with the array.
template <typename T>
py::array_t<T> to_numpy(std::vector<T>&& v, std::vector<py::ssize_t> shape) {
    auto* heap = new std::vector<T>(std::move(v));
    py::capsule owner(heap, [](void* p) { delete static_cast<std::vector<T>*>(p); });
    return py::array_t<T>(shape, heap->data(), owner);
}

// A frame as (image (H,W,3) uint8, depth (H,W) float32, prim (H,W) int32, FrameStats).
inline py::tuple frame_tuple(Frame&& f) {
    const py::ssize_t h = f.height, w = f.width;
    return py::make_tuple(to_numpy(std::move(f.rgb), {h, w, 3}), to_numpy(std::move(f.depth), {h, w}),
                          to_numpy(std::move(f.prim), {h, w}), f.stats);
}

}  // namespace vastray::bindings

namespace vastray {
void bind_render_types(pybind11::module_& m);  // bindings_render.cpp
}
