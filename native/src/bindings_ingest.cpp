// Python bindings of the mesh parsers (vastray/mesh_text.h) and the read phase's native
// gathering (part of vastray.native; vastray/triangle_readers.py drives them).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "vastray/mesh_text.h"

namespace py = pybind11;
using namespace vastray::ingest;

namespace {

template <typename T>
py::array_t<T> to_numpy(std::vector<T>&& v, std::vector<py::ssize_t> shape) {
    auto* heap = new std::vector<T>(std::move(v));
    py::capsule owner(heap, [](void* p) { delete static_cast<std::vector<T>*>(p); });
    return py::array_t<T>(shape, heap->data(), owner);
}

py::list statements(const std::vector<Statement>& s) {
    py::list out;
    for (const Statement& st : s) out.append(py::make_tuple(st.keyword, st.text));
    return out;
}

py::object error(const ParseError& e) {
    if (e.line == 0) return py::none();
    return py::make_tuple(e.line, e.what);
}

// A read-only contiguous byte view of bytes, bytearray, memoryview or a uint8 array.
struct Bytes {
    py::buffer_info info;
    explicit Bytes(const py::buffer& b) : info(b.request()) {
        if (info.itemsize != 1 || info.ndim != 1 || (info.strides.size() == 1 && info.strides[0] != 1)) {
            throw std::invalid_argument("expected a contiguous byte buffer");
        }
    }
    const std::uint8_t* data() const { return static_cast<const std::uint8_t*>(info.ptr); }
    std::size_t size() const { return static_cast<std::size_t>(info.size); }
};

py::dict obj_chunk(const py::buffer& data, std::int64_t vertices_before) {
    const Bytes b(data);
    ObjChunk c;
    {
        py::gil_scoped_release release;
        c = parse_obj(reinterpret_cast<const char*>(b.data()), b.size(), vertices_before);
    }
    py::dict d;
    const auto nv = static_cast<py::ssize_t>(c.vertices.size() / 3);
    const auto nt = static_cast<py::ssize_t>(c.triangles.size() / 3);
    d["vertices"] = to_numpy(std::move(c.vertices), {nv, 3});
    d["vertex_colours"] = c.vertex_colours.empty() ? py::object(py::none()) : py::object(to_numpy(std::move(c.vertex_colours), {nv, 3}));
    d["triangles"] = to_numpy(std::move(c.triangles), {nt, 3});
    d["triangle_statement"] = to_numpy(std::move(c.triangle_statement), {nt});
    d["triangle_face"] = to_numpy(std::move(c.triangle_face), {nt});
    d["statements"] = statements(c.statements);
    d["lines"] = c.lines;
    d["faces"] = c.faces;
    d["error"] = error(c.error);
    return d;
}

PlyType ply_type(const std::string& name) {
    static const std::pair<const char*, PlyType> names[] = {
        {"char", I8}, {"int8", I8}, {"uchar", U8}, {"uint8", U8}, {"short", I16}, {"int16", I16},
        {"ushort", U16}, {"uint16", U16}, {"int", I32}, {"int32", I32}, {"uint", U32}, {"uint32", U32},
        {"float", F32}, {"float32", F32}, {"double", F64}, {"float64", F64}};
    for (const auto& [n, t] : names) {
        if (name == n) return t;
    }
    throw std::invalid_argument("unknown PLY type '" + name + "'");
}

// props: (kind, keep) with kind a type name for scalars or ("list", count type, value type).
py::dict ply_rows(const py::buffer& data, std::size_t max_rows, const py::list& props, const std::string& format,
                  bool at_end) {
    std::vector<PlyProperty> ps;
    for (const py::handle& h : props) {
        const auto t = h.cast<py::tuple>();
        PlyProperty p;
        const auto kind = t[0].cast<std::vector<std::string>>();
        p.keep = t[1].cast<bool>();
        if (kind.size() == 3 && kind[0] == "list") {
            p.list = true;
            p.count_type = ply_type(kind[1]);
            p.value_type = ply_type(kind[2]);
        } else if (kind.size() == 1) {
            p.value_type = ply_type(kind[0]);
        } else {
            throw std::invalid_argument("bad PLY property description");
        }
        ps.push_back(p);
    }
    const PlyFormat f = format == "ascii" ? Ascii : format == "binary_little_endian" ? BinaryLittle
                        : format == "binary_big_endian"                       ? BinaryBig
                                                                                : throw std::invalid_argument("unknown PLY format " + format);
    const Bytes b(data);
    PlyRows r;
    {
        py::gil_scoped_release release;
        r = parse_ply_rows(b.data(), b.size(), max_rows, ps, f, at_end);
    }
    std::size_t kept = 0;
    for (const PlyProperty& p : ps) kept += (!p.list && p.keep) ? 1 : 0;
    py::dict d;
    d["rows"] = r.rows;
    d["consumed"] = r.consumed;
    d["scalars"] = to_numpy(std::move(r.scalars), {static_cast<py::ssize_t>(r.rows), static_cast<py::ssize_t>(kept)});
    const auto nc = static_cast<py::ssize_t>(r.list_counts.size());
    const auto nvals = static_cast<py::ssize_t>(r.list_values.size());
    d["list_counts"] = to_numpy(std::move(r.list_counts), {nc});
    d["list_values"] = to_numpy(std::move(r.list_values), {nvals});
    d["error"] = error(r.error);
    return d;
}

using Int64Array = py::array_t<std::int64_t, py::array::c_style | py::array::forcecast>;

py::tuple triangulate(const std::string& kind, Int64Array counts, Int64Array values) {
    const auto rows = static_cast<std::size_t>(counts.size());
    std::int64_t total = 0;
    const std::int64_t* c = counts.data();
    for (std::size_t r = 0; r < rows; ++r) {
        if (c[r] < 0) throw std::invalid_argument("negative list length");
        total += c[r];
    }
    if (total != values.size()) throw std::invalid_argument("list lengths do not match the values");
    Triangulated t;
    {
        py::gil_scoped_release release;
        if (kind == "fan") {
            t = triangulate_fans(c, rows, values.data());
        } else if (kind == "strip") {
            t = triangulate_strips(c, rows, values.data());
        } else {
            throw std::invalid_argument("triangulate: kind is 'fan' or 'strip'");
        }
    }
    const auto n = static_cast<py::ssize_t>(t.rows.size());
    return py::make_tuple(to_numpy(std::move(t.triangles), {n, 3}), to_numpy(std::move(t.rows), {n}), t.bad_row);
}

py::dict ascii_stl_chunk(const py::buffer& data, bool at_end) {
    const Bytes b(data);
    StlChunk c;
    {
        py::gil_scoped_release release;
        c = parse_ascii_stl(reinterpret_cast<const char*>(b.data()), b.size(), at_end);
    }
    const auto n = static_cast<py::ssize_t>(c.corners.size() / 9);
    py::dict d;
    d["corners"] = to_numpy(std::move(c.corners), {n, 3, 3});
    d["facet_statement"] = to_numpy(std::move(c.facet_statement), {n});
    d["statements"] = statements(c.statements);
    d["consumed"] = c.consumed;
    d["lines"] = c.lines;
    d["error"] = error(c.error);
    return d;
}

py::dict off_faces(const py::buffer& data, std::size_t max_rows, bool at_end) {
    const Bytes b(data);
    OffFaces f;
    {
        py::gil_scoped_release release;
        f = parse_off_faces(reinterpret_cast<const char*>(b.data()), b.size(), max_rows, at_end);
    }
    py::dict d;
    d["rows"] = f.rows;
    d["consumed"] = f.consumed;
    const auto nc = static_cast<py::ssize_t>(f.counts.size());
    const auto nv = static_cast<py::ssize_t>(f.values.size());
    d["list_counts"] = to_numpy(std::move(f.counts), {nc});
    d["list_values"] = to_numpy(std::move(f.values), {nv});
    d["colours"] = to_numpy(std::move(f.colours), {static_cast<py::ssize_t>(f.rows), 4});
    d["error"] = error(f.error);
    return d;
}

}  // namespace

void bind_ingest(py::module_& m) {
    m.def("off_faces", &off_faces, py::arg("data"), py::arg("max_rows"), py::arg("at_end"),
          "Parse OFF face rows (one a line, optional colour after the indices)");
    m.def("obj_chunk", &obj_chunk, py::arg("data"), py::arg("vertices_before"),
          "Parse whole lines of an OBJ file: vertices, fan-triangulated faces, naming statements");
    m.def("ply_rows", &ply_rows, py::arg("data"), py::arg("max_rows"), py::arg("props"), py::arg("format"),
          py::arg("at_end"), "Parse rows of one PLY element (ASCII or binary)");
    m.def("triangulate", &triangulate, py::arg("kind"), py::arg("counts"), py::arg("values"),
          "Triangles of PLY polygon lists ('fan') or triangle strips with -1 restarts ('strip')");
    m.def("ascii_stl_chunk", &ascii_stl_chunk, py::arg("data"), py::arg("at_end"),
          "Parse the complete facets of an ASCII STL chunk");
}
