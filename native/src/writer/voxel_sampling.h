// LOD voxels (docs/FORMAT.md §10 and §15): what a viewer outside each face of a LOD
// node's cell sees of the finished level below, and its quantisation into 1 or 6 samples.
//
// The level below is seen through proxies: each leaf and each voxel of a finished
// treelet becomes a box with six face samples. A voxel is sampled by casting a grid of
// orthographic rays per face against its children's proxies, not against triangles.
#pragma once

#include <cstdint>
#include <vector>

#include "vastray/vecmath.h"

namespace vastray::writer {

struct TriangleSource;  // triangle_blocks.h

// Face f = 2 * axis + side: side 0 is the face at the low end of the axis (looked at
// from -axis), side 1 the high one. A sample for face f describes what a viewer outside
// that face sees, so its normal is oriented towards the viewer (dot(n, outward_f) >= 0).
inline Vec3f outward(int f) {
    Vec3f o;
    o[f / 2] = (f % 2) != 0 ? 1.0f : -1.0f;
    return o;
}

struct FaceSamples {
    Vec3f colour[6];
    Vec3f normal[6];
};

// What a finished treelet looks like to the LOD node above it.
struct Proxy {
    Box3f box;
    FaceSamples s;
};

// A triangle's unit normal and area. A triangle is referenced by several leaves, so a
// part computes these once per triangle for all its leaf proxies.
struct Facet {
    Vec3f normal;  // undefined unless area > 0
    float area = 0;
};
Facet facet_of(const Vec3f* corners);

// The proxy of a leaf: its triangles' box (clipped to the cell) with area-weighted
// colours and normals per face (grey without colours).
Proxy leaf_proxy(const TriangleSource& src, const std::uint32_t* tris, std::uint32_t count, const Box3f& cell);

// Samples a voxel filling `cell` from the proxies of its (at most two) child treelets;
// either may be null. `rays` per axis and face (clamped to 1 ... 8).
FaceSamples sample_voxel(const Box3f& cell, const std::vector<Proxy>* a, const std::vector<Proxy>* b, int rays);

// The stored form of a voxel: one sample when all faces agree within the tolerances
// (normals up to sign: shading is two-sided), else six; six that show at most two
// colours take four words when `packed` (format::pack_voxel), the same samples.
struct QuantisedVoxel {
    std::uint32_t words[6] = {};
    int count = 0;  // words: 1, 4 or 6
    FaceSamples seen;  // what the level above samples (the one-sample value on every face)
};
QuantisedVoxel quantise_voxel(const FaceSamples& s, float colour_tolerance, float normal_tolerance, bool packed);

}  // namespace vastray::writer
