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

// tmin of ray queries: a ray starts at its origin, so a tmin below 0 counts as 0 (the
// walks never visit cells or boxes behind the origin). NaN stays NaN: an invalid ray.
inline std::vector<double> ray_starts(const py::object& tmin, std::size_t n) {
    std::vector<double> t = broadcast(tmin, n, "tmin");
    for (double& v : t) {
        if (v < 0) v = 0;
    }
    return t;
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

// Highlight runs as Python gives them: an (N, 2) integer array or a list of pairs.
inline std::vector<TriangleRange> to_ranges(const py::object& ranges) {
    using Int64Array = py::array_t<std::int64_t, py::array::c_style | py::array::forcecast>;
    const auto arr = Int64Array::ensure(ranges);
    if (!arr) throw std::invalid_argument("highlight must be an (N, 2) array of triangle id runs");
    if (arr.size() == 0) return {};
    if (arr.ndim() != 2 || arr.shape(1) != 2) {
        throw std::invalid_argument("highlight must be an (N, 2) array of triangle id runs [first, end)");
    }
    std::vector<TriangleRange> out(static_cast<std::size_t>(arr.shape(0)));
    const std::int64_t* v = arr.data();
    for (std::size_t i = 0; i < out.size(); ++i) {
        const std::int64_t first = v[2 * i], end = v[2 * i + 1];
        if (first < 0 || end > std::int64_t{0xFFFFFFFF}) {
            throw std::invalid_argument("highlight runs must hold triangle ids in [0, 2^32)");
        }
        out[i] = {static_cast<std::uint32_t>(first), static_cast<std::uint32_t>(end)};
    }
    return out;
}
// Hands a vector to numpy without a copy; the capsule frees it with the array.
template <typename T, typename Allocator>
py::array_t<T> to_numpy(std::vector<T, Allocator>&& v, std::vector<py::ssize_t> shape) {
    using Vector = std::vector<T, Allocator>;
    auto* heap = new Vector(std::move(v));
    py::capsule owner(heap, [](void* p) { delete static_cast<Vector*>(p); });
    return py::array_t<T>(shape, heap->data(), owner);
}

inline py::array_t<std::int64_t> from_ranges(const std::vector<TriangleRange>& ranges) {
    std::vector<std::int64_t> flat;
    flat.reserve(2 * ranges.size());
    for (const auto& r : ranges) {
        flat.push_back(r.first);
        flat.push_back(r.end);
    }
    const auto n = static_cast<py::ssize_t>(ranges.size());
    return to_numpy(std::move(flat), {n, 2});
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
