// Parsers for the mesh files the builder streams (vastray/triangle_readers.py drives them
// chunk by chunk): OBJ, PLY elements (ASCII and binary of either byte order, with list
// properties), ASCII STL, and the triangulation of PLY faces and strips. They parse
// numbers and structure only; names (OBJ parts, STL solids) go back to the caller as
// statements, and every error carries the line (or row) it was found on.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace vastray::ingest {

// A statement that names something (OBJ o/g/usemtl/mtllib, STL solid): its keyword and
// the rest of its line. Triangles record how many statements preceded them in the chunk.
struct Statement {
    std::string keyword, text;
};

struct ParseError {
    std::uint64_t line = 0;  // 1-based within the chunk (0: no error)
    std::string what;
};

// ---- OBJ -------------------------------------------------------------------------------
struct ObjChunk {
    std::vector<double> vertices;        // x, y, z per vertex
    std::vector<float> vertex_colours;   // r, g, b per vertex (0..1) when any vertex in the chunk has them; NaN where absent
    std::vector<std::int64_t> triangles;  // three absolute 0-based vertex indices per triangle
    std::vector<std::uint32_t> triangle_statement;  // statements before the triangle in this chunk
    std::vector<std::uint32_t> triangle_face;       // the face (f line) of the chunk it came from
    std::vector<Statement> statements;
    std::uint64_t lines = 0, faces = 0;
    ParseError error;
};

// Parses whole lines of an OBJ file. `vertices_before` counts the vertices of earlier
// chunks (negative indices are relative to the vertices defined so far). Polygons are
// fan-triangulated in file order. Lines other than v, f, o, g, usemtl and mtllib (vt, vn,
// s, l, p, comments, ...) are skipped.
ObjChunk parse_obj(const char* data, std::size_t size, std::int64_t vertices_before);

// ---- PLY elements ----------------------------------------------------------------------
enum PlyType : int { I8, U8, I16, U16, I32, U32, F32, F64 };
enum PlyFormat : int { Ascii, BinaryLittle, BinaryBig };

struct PlyProperty {
    bool list = false;
    PlyType count_type = U8;  // list length type
    PlyType value_type = F32;
    bool keep = true;         // scalars: returned; lists: the one list returned (at most one kept)
};

struct PlyRows {
    std::size_t rows = 0;       // complete rows parsed
    std::size_t consumed = 0;   // bytes those rows took
    std::vector<double> scalars;              // kept scalar properties, row-major
    std::vector<std::int64_t> list_counts;    // the kept list's length per row
    std::vector<std::int64_t> list_values;    // its values, concatenated
    ParseError error;           // line counts rows (ASCII: one row per line)
};

// Parses up to `max_rows` rows of one element from `data`. A row cut off by the end of
// the buffer is left for the next call unless `at_end` (then it is an error).
PlyRows parse_ply_rows(const std::uint8_t* data, std::size_t size, std::size_t max_rows,
                       const std::vector<PlyProperty>& props, PlyFormat format, bool at_end);

// ---- triangulation ---------------------------------------------------------------------
// Polygons (each row's list, at least 3 vertices) as fans (v0, vi, vi+1); triangle
// strips (a list with -1 restarts) as runs whose odd triangles swap their first two
// corners, so every triangle keeps the strip's winding. Returns the triangles and, per
// triangle, the row it came from.
struct Triangulated {
    std::vector<std::int64_t> triangles;
    std::vector<std::uint64_t> rows;
    std::int64_t bad_row = -1;  // fans: a row with fewer than 3 vertices
};
Triangulated triangulate_fans(const std::int64_t* counts, std::size_t rows, const std::int64_t* values);
Triangulated triangulate_strips(const std::int64_t* counts, std::size_t rows, const std::int64_t* values);

// ---- OFF faces -------------------------------------------------------------------------
// Rows "n i0 ... i(n-1) [r g b [a]]", one per line; the colour, when present, is what
// follows the indices on the line (integers 0-255, or floats 0-1).
struct OffFaces {
    std::size_t rows = 0, consumed = 0;
    std::vector<std::int64_t> counts, values;
    std::vector<double> colours;  // 4 per row (NaN where the row has none)
    ParseError error;
};
OffFaces parse_off_faces(const char* data, std::size_t size, std::size_t max_rows, bool at_end);

// ---- ASCII STL -------------------------------------------------------------------------
struct StlChunk {
    std::vector<double> corners;  // 9 per facet
    std::vector<std::uint32_t> facet_statement;  // solids started before the facet in this chunk
    std::vector<Statement> statements;            // solid NAME
    std::size_t consumed = 0;                     // bytes of whole facets (and statements) parsed
    std::uint64_t lines = 0;
    ParseError error;
};
// Parses facets up to the last complete one in `data` (all of it when `at_end`).
StlChunk parse_ascii_stl(const char* data, std::size_t size, bool at_end);

}  // namespace vastray::ingest
