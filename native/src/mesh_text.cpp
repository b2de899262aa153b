#include "vastray/mesh_text.h"

#include <charconv>
#include <cmath>
#include <cstring>
#include <limits>

namespace vastray::ingest {

namespace {

bool is_space(char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\f' || c == '\v'; }

// A cursor over one line: `end` is the newline (or the buffer's end).
struct Line {
    const char* p;
    const char* end;

    // Newlines inside a line come from continuations (a backslash before the newline),
    // which count as spaces.
    void skip_space() {
        while (p < end) {
            if (is_space(*p) || *p == '\n') {
                ++p;
            } else if (*p == '\\' && continues(p + 1)) {
                ++p;
            } else {
                break;
            }
        }
    }
    bool continues(const char* q) const {
        if (q < end && *q == '\r') ++q;
        return q >= end || *q == '\n';
    }
    bool done() {
        skip_space();
        return p >= end;
    }
    // The next whitespace-separated token.
    std::string_view token() {
        skip_space();
        const char* start = p;
        while (p < end && !is_space(*p) && *p != '\n') ++p;
        return {start, static_cast<std::size_t>(p - start)};
    }
    bool number(double& out) {
        skip_space();
        const char* start = p;
        if (p < end && *p == '+') ++p;  // from_chars takes no leading '+'
        const auto r = std::from_chars(p, end, out);
        if (r.ec != std::errc() || (r.ptr < end && !is_space(*r.ptr) && *r.ptr != '\n' && *r.ptr != '\\')) {
            p = start;
            return false;
        }
        p = r.ptr;
        return true;
    }
    bool integer(std::int64_t& out) {
        skip_space();
        const char* start = p;
        if (p < end && *p == '+') ++p;
        const auto r = std::from_chars(p, end, out);
        if (r.ec != std::errc()) {
            p = start;
            return false;
        }
        p = r.ptr;
        return true;
    }
    std::string rest() {
        skip_space();
        const char* e = end;
        while (e > p && (is_space(e[-1]) || e[-1] == '\\')) --e;
        return std::string(p, static_cast<std::size_t>(e - p));
    }
};

// The end of the line starting at p. A backslash right before the newline continues the
// line (OBJ allows it); the newline then counts as a space.
const char* line_end(const char* p, const char* end, std::uint64_t& extra_lines) {
    for (;;) {
        const char* nl = static_cast<const char*>(std::memchr(p, '\n', static_cast<std::size_t>(end - p)));
        if (nl == nullptr) return end;
        const char* before = nl;
        if (before > p && before[-1] == '\r') --before;
        if (before > p && before[-1] == '\\') {
            ++extra_lines;
            p = nl + 1;
            continue;
        }
        return nl;
    }
}

std::string shown(std::string_view s) {
    std::string out(s.substr(0, 40));
    if (s.size() > 40) out += "...";
    return out;
}

}  // namespace

ObjChunk parse_obj(const char* data, std::size_t size, std::int64_t vertices_before) {
    ObjChunk out;
    out.vertices.reserve(size / 12);
    out.triangles.reserve(size / 6);
    const char* p = data;
    const char* const end = data + size;
    std::uint64_t line_no = 0;
    bool colours = false;
    std::vector<std::int64_t> face;
    auto fail = [&](const std::string& what) {
        out.error = {line_no, what};
        return out;
    };
    while (p < end) {
        std::uint64_t continued = 0;
        const char* e = line_end(p, end, continued);
        ++line_no;
        Line line{p, e};
        p = e < end ? e + 1 : end;
        const std::string_view key = line.token();
        if (key.empty() || key[0] == '#') {
            line_no += continued;
            continue;
        }
        if (key == "v") {
            double v[7];
            int n = 0;
            while (n < 7 && line.number(v[n])) ++n;
            if (n < 3) return fail("a vertex needs three coordinates (x y z)");
            if (!line.done()) return fail("cannot read a number: '" + shown(line.token()) + "'");
            out.vertices.insert(out.vertices.end(), v, v + 3);
            const bool rgb = n == 6 || n == 7;
            if (rgb && !colours) {
                colours = true;
                out.vertex_colours.assign(out.vertices.size() - 3, std::numeric_limits<float>::quiet_NaN());
            }
            if (colours) {
                for (int k = 0; k < 3; ++k) {
                    out.vertex_colours.push_back(rgb ? static_cast<float>(v[3 + k]) : std::numeric_limits<float>::quiet_NaN());
                }
            }
        } else if (key == "f") {
            face.clear();
            const std::int64_t defined = vertices_before + static_cast<std::int64_t>(out.vertices.size() / 3);
            while (!line.done()) {
                std::int64_t idx = 0;
                const char* token_start = line.p;
                if (!line.integer(idx)) return fail("cannot read a face vertex: '" + shown(line.token()) + "'");
                while (line.p < line.end && !is_space(*line.p) && *line.p != '\n') ++line.p;  // the /vt/vn part
                if (idx == 0) return fail("vertex index 0 in a face (OBJ counts vertices from 1)");
                if (idx < 0) {
                    if (-idx > defined) {
                        return fail("relative vertex index " + std::string(token_start, static_cast<std::size_t>(line.p - token_start)) +
                                    " reaches before the first vertex");
                    }
                    idx = defined + idx;
                } else {
                    idx -= 1;
                }
                face.push_back(idx);
            }
            if (face.size() < 3) return fail("a face needs at least three vertices");
            const auto statement = static_cast<std::uint32_t>(out.statements.size());
            for (std::size_t k = 1; k + 1 < face.size(); ++k) {
                out.triangles.push_back(face[0]);
                out.triangles.push_back(face[k]);
                out.triangles.push_back(face[k + 1]);
                out.triangle_statement.push_back(statement);
                out.triangle_face.push_back(static_cast<std::uint32_t>(out.faces));
            }
            ++out.faces;
        } else if (key == "o" || key == "g" || key == "usemtl" || key == "mtllib") {
            out.statements.push_back({std::string(key), line.rest()});
        }
        line_no += continued;
    }
    if (colours && out.vertex_colours.size() != out.vertices.size()) {
        out.vertex_colours.resize(out.vertices.size(), std::numeric_limits<float>::quiet_NaN());
    }
    out.lines = line_no;
    return out;
}

namespace {

std::size_t type_size(PlyType t) {
    switch (t) {
        case I8: case U8: return 1;
        case I16: case U16: return 2;
        case I32: case U32: case F32: return 4;
        case F64: return 8;
    }
    return 0;
}

template <typename T>
T load(const std::uint8_t* p, bool swap) {
    std::uint8_t b[sizeof(T)];
    std::memcpy(b, p, sizeof(T));
    if (swap) {
        for (std::size_t i = 0; i < sizeof(T) / 2; ++i) std::swap(b[i], b[sizeof(T) - 1 - i]);
    }
    T v;
    std::memcpy(&v, b, sizeof(T));
    return v;
}

double binary_value(const std::uint8_t* p, PlyType t, bool swap) {
    switch (t) {
        case I8: return static_cast<std::int8_t>(*p);
        case U8: return *p;
        case I16: return load<std::int16_t>(p, swap);
        case U16: return load<std::uint16_t>(p, swap);
        case I32: return load<std::int32_t>(p, swap);
        case U32: return load<std::uint32_t>(p, swap);
        case F32: return load<float>(p, swap);
        case F64: return load<double>(p, swap);
    }
    return 0;
}

std::int64_t binary_index(const std::uint8_t* p, PlyType t, bool swap) {
    switch (t) {
        case I8: return static_cast<std::int8_t>(*p);
        case U8: return *p;
        case I16: return load<std::int16_t>(p, swap);
        case U16: return load<std::uint16_t>(p, swap);
        case I32: return load<std::int32_t>(p, swap);
        case U32: return load<std::uint32_t>(p, swap);
        case F32: return static_cast<std::int64_t>(load<float>(p, swap));
        case F64: return static_cast<std::int64_t>(load<double>(p, swap));
    }
    return 0;
}

bool is_float(PlyType t) { return t == F32 || t == F64; }

// ASCII tokens across lines (a row may in principle span lines; files write one a line).
struct Tokens {
    const char* p;
    const char* end;
    std::uint64_t line = 1;

    bool next(std::string_view& tok) {
        while (p < end && (is_space(*p) || *p == '\n')) {
            if (*p == '\n') ++line;
            ++p;
        }
        if (p >= end) return false;
        const char* s = p;
        while (p < end && !is_space(*p) && *p != '\n') ++p;
        tok = {s, static_cast<std::size_t>(p - s)};
        return true;
    }
};

bool to_double(std::string_view tok, double& v) {
    const char* s = tok.data();
    const char* e = s + tok.size();
    if (s < e && *s == '+') ++s;
    const auto r = std::from_chars(s, e, v);
    return r.ec == std::errc() && r.ptr == e;
}

bool to_int(std::string_view tok, std::int64_t& v) {
    const char* s = tok.data();
    const char* e = s + tok.size();
    if (s < e && *s == '+') ++s;
    const auto r = std::from_chars(s, e, v);
    if (r.ec == std::errc() && r.ptr == e) return true;
    double d;  // some writers put integers as "3.0"
    if (!to_double(tok, d) || d != std::floor(d) || std::abs(d) > 9e15) return false;
    v = static_cast<std::int64_t>(d);
    return true;
}

}  // namespace

PlyRows parse_ply_rows(const std::uint8_t* data, std::size_t size, std::size_t max_rows,
                       const std::vector<PlyProperty>& props, PlyFormat format, bool at_end) {
    PlyRows out;
    std::size_t kept_scalars = 0;
    for (const PlyProperty& pr : props) kept_scalars += (!pr.list && pr.keep) ? 1 : 0;
    out.scalars.reserve(kept_scalars * std::min<std::size_t>(max_rows, 1 << 20));
    if (format == Ascii) {
        Tokens t{reinterpret_cast<const char*>(data), reinterpret_cast<const char*>(data) + size};
        std::string_view tok;
        while (out.rows < max_rows) {
            const std::size_t scalars0 = out.scalars.size(), counts0 = out.list_counts.size(), values0 = out.list_values.size();
            bool complete = true;
            for (const PlyProperty& pr : props) {
                if (!t.next(tok)) {
                    complete = false;
                    break;
                }
                if (!pr.list) {
                    double v;
                    if (!to_double(tok, v)) {
                        out.error = {out.rows + 1, "cannot read a number: '" + shown(tok) + "'"};
                        return out;
                    }
                    if (pr.keep) out.scalars.push_back(v);
                    continue;
                }
                std::int64_t n;
                if (!to_int(tok, n) || n < 0) {
                    out.error = {out.rows + 1, "cannot read a list length: '" + shown(tok) + "'"};
                    return out;
                }
                if (pr.keep) out.list_counts.push_back(n);
                for (std::int64_t k = 0; k < n; ++k) {
                    if (!t.next(tok)) {
                        complete = false;
                        break;
                    }
                    if (!pr.keep) continue;
                    std::int64_t v;
                    if (!to_int(tok, v)) {
                        out.error = {out.rows + 1, "cannot read a vertex index: '" + shown(tok) + "'"};
                        return out;
                    }
                    out.list_values.push_back(v);
                }
                if (!complete) break;
            }
            if (!complete) {
                out.scalars.resize(scalars0);
                out.list_counts.resize(counts0);
                out.list_values.resize(values0);
                if (at_end) out.error = {out.rows + 1, "the file ends inside this row"};
                return out;
            }
            ++out.rows;
            out.consumed = static_cast<std::size_t>(t.p - reinterpret_cast<const char*>(data));
        }
        return out;
    }
    const bool swap = format == BinaryBig;
    std::size_t at = 0;
    while (out.rows < max_rows) {
        const std::size_t scalars0 = out.scalars.size(), counts0 = out.list_counts.size(), values0 = out.list_values.size();
        std::size_t q = at;
        bool complete = true;
        for (const PlyProperty& pr : props) {
            if (!pr.list) {
                const std::size_t w = type_size(pr.value_type);
                if (q + w > size) {
                    complete = false;
                    break;
                }
                if (pr.keep) out.scalars.push_back(binary_value(data + q, pr.value_type, swap));
                q += w;
                continue;
            }
            const std::size_t cw = type_size(pr.count_type), vw = type_size(pr.value_type);
            if (q + cw > size) {
                complete = false;
                break;
            }
            const std::int64_t n = binary_index(data + q, pr.count_type, swap);
            q += cw;
            if (n < 0) {
                out.error = {out.rows + 1, "negative list length"};
                return out;
            }
            if (q + static_cast<std::size_t>(n) * vw > size) {
                complete = false;
                break;
            }
            if (pr.keep) {
                if (is_float(pr.value_type)) {
                    out.error = {out.rows + 1, "vertex indices stored as floating point"};
                    return out;
                }
                out.list_counts.push_back(n);
                for (std::int64_t k = 0; k < n; ++k) out.list_values.push_back(binary_index(data + q + static_cast<std::size_t>(k) * vw, pr.value_type, swap));
            }
            q += static_cast<std::size_t>(n) * vw;
        }
        if (!complete) {
            out.scalars.resize(scalars0);
            out.list_counts.resize(counts0);
            out.list_values.resize(values0);
            if (at_end) out.error = {out.rows + 1, "the file ends inside this row"};
            return out;
        }
        at = q;
        ++out.rows;
        out.consumed = at;
    }
    return out;
}

Triangulated triangulate_fans(const std::int64_t* counts, std::size_t rows, const std::int64_t* values) {
    Triangulated out;
    std::size_t at = 0;
    for (std::size_t r = 0; r < rows; ++r) {
        const auto n = static_cast<std::size_t>(counts[r]);
        if (n < 3) {
            out.bad_row = static_cast<std::int64_t>(r);
            return out;
        }
        for (std::size_t k = 1; k + 1 < n; ++k) {
            out.triangles.push_back(values[at]);
            out.triangles.push_back(values[at + k]);
            out.triangles.push_back(values[at + k + 1]);
            out.rows.push_back(r);
        }
        at += n;
    }
    return out;
}

Triangulated triangulate_strips(const std::int64_t* counts, std::size_t rows, const std::int64_t* values) {
    Triangulated out;
    std::size_t at = 0;
    for (std::size_t r = 0; r < rows; ++r) {
        const auto n = static_cast<std::size_t>(counts[r]);
        std::size_t run = 0;  // vertices in the current run (restarted by -1)
        for (std::size_t k = 0; k < n; ++k) {
            const std::int64_t v = values[at + k];
            if (v < 0) {
                run = 0;
                continue;
            }
            ++run;
            if (run < 3) continue;
            const std::int64_t a = values[at + k - 2], b = values[at + k - 1];
            const bool odd = (run - 3) % 2 == 1;
            out.triangles.push_back(odd ? b : a);
            out.triangles.push_back(odd ? a : b);
            out.triangles.push_back(v);
            out.rows.push_back(r);
        }
        at += n;
    }
    return out;
}

OffFaces parse_off_faces(const char* data, std::size_t size, std::size_t max_rows, bool at_end) {
    OffFaces out;
    const char* p = data;
    const char* const end = data + size;
    const double nan = std::numeric_limits<double>::quiet_NaN();
    while (p < end && out.rows < max_rows) {
        const char* nl = static_cast<const char*>(std::memchr(p, '\n', static_cast<std::size_t>(end - p)));
        if (nl == nullptr && !at_end) break;
        const char* e = nl == nullptr ? end : nl;
        Line line{p, e};
        const char* next = nl == nullptr ? end : nl + 1;
        const std::string_view first = line.token();
        if (first.empty() || first[0] == '#') {
            p = next;
            out.consumed = static_cast<std::size_t>(p - data);
            continue;
        }
        std::int64_t n;
        if (!to_int(first, n) || n < 0) {
            out.error = {out.rows + 1, "cannot read a face's vertex count: '" + shown(first) + "'"};
            return out;
        }
        out.counts.push_back(n);
        for (std::int64_t k = 0; k < n; ++k) {
            std::int64_t v;
            const std::string_view tok = line.token();
            if (tok.empty() || !to_int(tok, v)) {
                out.error = {out.rows + 1, tok.empty() ? "a face lists fewer vertices than its count" : "cannot read a vertex index: '" + shown(tok) + "'"};
                return out;
            }
            out.values.push_back(v);
        }
        double c[4] = {nan, nan, nan, nan};
        int m = 0;
        while (!line.done()) {
            double v;
            if (m >= 4 || !line.number(v)) {
                out.error = {out.rows + 1, "unexpected values after a face's colour"};
                return out;
            }
            c[m++] = v;
        }
        if (m != 0 && m != 3 && m != 4) {
            out.error = {out.rows + 1, "a face colour needs three or four values"};
            return out;
        }
        out.colours.insert(out.colours.end(), c, c + 4);
        ++out.rows;
        p = next;
        out.consumed = static_cast<std::size_t>(p - data);
    }
    return out;
}

StlChunk parse_ascii_stl(const char* data, std::size_t size, bool at_end) {
    StlChunk out;
    const char* p = data;
    const char* const end = data + size;
    std::uint64_t line_no = 0;
    double facet[9];
    int corners = -1;  // -1: outside a facet
    std::size_t facets_done = 0, statements_done = 0;
    auto fail = [&](const std::string& what) {
        out.error = {line_no, what};
        return out;
    };
    while (p < end) {
        const char* nl = static_cast<const char*>(std::memchr(p, '\n', static_cast<std::size_t>(end - p)));
        const char* e = nl == nullptr ? end : nl;
        if (nl == nullptr && !at_end) break;  // a partial last line waits for the next chunk
        ++line_no;
        Line line{p, e};
        const char* next = nl == nullptr ? end : nl + 1;
        const std::string_view key = line.token();
        if (key == "vertex") {
            if (corners < 0 || corners >= 3) return fail("a vertex outside a facet's loop of three");
            for (int k = 0; k < 3; ++k) {
                if (!line.number(facet[3 * corners + k])) return fail("a vertex needs three coordinates (x y z)");
            }
            ++corners;
        } else if (key == "facet") {
            if (corners >= 0) return fail("a facet inside a facet");
            corners = 0;
        } else if (key == "endfacet") {
            if (corners != 3) return fail("a facet needs three vertices, this one has " + std::to_string(std::max(corners, 0)));
            out.corners.insert(out.corners.end(), facet, facet + 9);
            out.facet_statement.push_back(static_cast<std::uint32_t>(out.statements.size()));
            corners = -1;
        } else if (key == "solid") {
            if (corners >= 0) return fail("'solid' inside a facet");
            out.statements.push_back({"solid", line.rest()});
        } else if (!(key.empty() || key == "outer" || key == "endloop" || key == "endsolid")) {
            return fail("unexpected '" + shown(key) + "' in an ASCII STL file");
        }
        p = next;
        if (corners < 0) {
            facets_done = out.corners.size();
            statements_done = out.statements.size();
            out.consumed = static_cast<std::size_t>(p - data);
            out.lines = line_no;
        }
    }
    if (corners >= 0) {
        if (at_end) return fail("the file ends inside a facet");
        out.corners.resize(facets_done);
        out.facet_statement.resize(facets_done / 9);
        out.statements.resize(statements_done);
    }
    return out;
}

}  // namespace vastray::ingest
