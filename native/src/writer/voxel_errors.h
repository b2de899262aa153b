// Surface errors of LOD voxels (docs/FORMAT.md §15, "Voxel errors"; FLAG_VOXEL_ERRORS).
//
// A voxel draws its node's whole cell as a box. What that costs in the image is how far
// the box's surface lies from the geometry it stands in for: a box around a thin pipe
// lies on the pipe however long the box is, a box around a diagonal pipe does not. The
// enclosing-sphere radius R (what the LOD test used alone before) says only how big the
// box is. For every kd node this computes E, an upper bound on
//     max over points b of the cell's surface of the distance from b to the triangles
//     of the node's subtree,
// bottom-up and conservatively:
//   - a leaf: the distance from a convex box to one triangle is largest at a corner of
//     the box (distance to a convex set is convex), so each triangle bounds the whole
//     cell by its largest corner distance, and the leaf takes its best triangle's;
//   - an inner node whose children are both present: the larger of their E (a point of
//     the cell's surface lies on the surface of the child holding it);
//   - one child empty: the empty half's width along the split axis plus the other
//     child's E (from a point in the empty half, straight to the split plane, which is
//     the other child's face).
// A node with no triangles below it has E = infinity.
#pragma once

#include <cstdint>
#include <vector>

#include "vastray/format.h"
#include "vastray/kdtree.h"
#include "vastray/vecmath.h"

namespace vastray::writer {

struct TriangleSource;  // triangle_blocks.h

// The Euclidean distance from p to the triangle v[0..2] (any triangle; a degenerate one
// counts as the segment or point it is, bounded by its nearest corner).
float point_triangle_distance(const Vec3f& p, const Vec3f* v);

// E of a leaf whose cell is `cell` (infinity with no triangles). The search over its
// triangles may stop at any bound no greater than `enough`.
float leaf_error(const TriangleSource& src, const std::uint32_t* tris, std::uint32_t count, const Box3f& cell,
                 float enough = 0.0f);

// E of an inner node from its children's (infinity for an absent child).
float inner_error(const Box3f& cell, int axis, float split, float left, float right);

// E of every node of a part's kd-tree (index as in tree.nodes), its root (a treelet
// root) in `cell`, the leaves shared out over `lanes` threads. A leaf's bound need not be
// tighter than `floor` times the radius of the LOD node above it (the least error the
// writer codes, ModelWriterParams::voxel_error_floor).
std::vector<float> kd_errors(const KdTree& tree, const TriangleSource& src, const Box3f& cell, float floor,
                             unsigned lanes);

}  // namespace vastray::writer
