#include "writer/voxel_errors.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "vastray/prefetch.h"
#include "vastray/thread_pool.h"
#include "writer/triangle_blocks.h"

namespace vastray::writer {

namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

Box3f half_of(const Box3f& cell, int axis, float split, int side) {
    Box3f c = cell;
    (side == 0 ? c.hi : c.lo)[axis] = split;
    return c;
}

// Where a walk of a part's kd-tree stands: a node, its cell, its depth in the part (whose
// root is a treelet root: a LOD node sits at depth 2 mod 3) and the radius of the
// nearest LOD node above it (0 above the part's first LOD node).
struct Place {
    std::uint32_t node;
    Box3f cell;
    int depth;
    float lod_radius;

    Place child(const KdNode& k, int side, std::uint32_t right_offset) const {
        const bool lod = depth % format::kTreeletHeight == format::kTreeletHeight - 1;
        return {side == 0 ? node + 1 : node + right_offset, half_of(cell, k.axis(), k.split(), side), depth + 1,
                lod ? format::cell_radius(cell.extent()) : lod_radius};
    }
};

// E of one subtree into out[]: its leaves first, in preorder, with the triangles a few
// leaves ahead prefetched (a part's records are in input order, so a leaf's triangles
// lie scattered), then its inner nodes from them. A leaf's search stops once its bound
// is below the floor of the LOD node above it: no LOD node's code can get smaller.
class SubtreeErrors {
public:
    SubtreeErrors(const KdTree& tree, const TriangleSource& src, float floor, float* out)
        : tree_(tree), src_(src), floor_(floor), out_(out) {}

    void run(const Place& root) {
        leaves_.clear();
        collect(root);
        constexpr std::size_t kAhead = 8;
        for (std::size_t j = 0; j < leaves_.size(); ++j) {
            if (j + kAhead < leaves_.size()) prefetch(leaves_[j + kAhead].node);
            const Place& p = leaves_[j];
            const KdNode& k = tree_.nodes[p.node];
            out_[p.node] = leaf_error(src_, tree_.tri_ids.data() + k.first(), k.count(), p.cell, floor_ * p.lod_radius);
        }
        combine(root);
    }

private:
    void collect(const Place& p) {
        const KdNode& k = tree_.nodes[p.node];
        if (k.is_leaf()) {
            leaves_.push_back(p);
            return;
        }
        if (!k.left_empty()) collect(p.child(k, 0, k.right_offset()));
        if (!k.right_empty()) collect(p.child(k, 1, k.right_offset()));
    }

    void prefetch(std::uint32_t leaf) const {
        const KdNode& k = tree_.nodes[leaf];
        const std::uint32_t* tris = tree_.tri_ids.data() + k.first();
        for (std::uint32_t t = 0; t < k.count(); ++t) {
            prefetch_line(src_.corners(tris[t]));
            prefetch_line(src_.facets + tris[t]);
        }
    }

    float combine(const Place& p) {
        const KdNode& k = tree_.nodes[p.node];
        if (k.is_leaf()) return out_[p.node];
        const float l = k.left_empty() ? kInf : combine(p.child(k, 0, k.right_offset()));
        const float r = k.right_empty() ? kInf : combine(p.child(k, 1, k.right_offset()));
        return out_[p.node] = inner_error(p.cell, k.axis(), k.split(), l, r);
    }

    const KdTree& tree_;
    const TriangleSource& src_;
    float floor_;
    float* out_;
    std::vector<Place> leaves_;
};

// The squared distance from p to the triangle v[0..2]: the closest point by the Voronoi
// regions of the corners, edges and face, in the usual barycentric form.
float distance2(const Vec3f& p, const Vec3f* v) {
    const Vec3f a = v[0], b = v[1], c = v[2];
    const Vec3f ab = b - a, ac = c - a, ap = p - a;
    const float d1 = dot(ab, ap), d2 = dot(ac, ap);
    if (d1 <= 0 && d2 <= 0) return dot(ap, ap);
    const Vec3f bp = p - b;
    const float d3 = dot(ab, bp), d4 = dot(ac, bp);
    if (d3 >= 0 && d4 <= d3) return dot(bp, bp);
    const float vc = d1 * d4 - d3 * d2;
    const Vec3f cp = p - c;
    const float d5 = dot(ab, cp), d6 = dot(ac, cp);
    const float vb = d5 * d2 - d1 * d6;
    const float va = d3 * d6 - d5 * d4;
    Vec3f q;
    if (vc <= 0 && d1 >= 0 && d3 <= 0) {
        q = a + ab * (d1 / (d1 - d3));
    } else if (d6 >= 0 && d5 <= d6) {
        return dot(cp, cp);
    } else if (vb <= 0 && d2 >= 0 && d6 <= 0) {
        q = a + ac * (d2 / (d2 - d6));
    } else if (va <= 0 && d4 - d3 >= 0 && d5 - d6 >= 0) {
        q = b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    } else {
        const float inv = 1.0f / (va + vb + vc);
        q = a + ab * (vb * inv) + ac * (vc * inv);
    }
    const float d = dot(p - q, p - q);
    // A degenerate triangle can divide by zero: its nearest corner still bounds it.
    if (!(d >= 0) || !std::isfinite(d)) return std::min({dot(ap, ap), dot(bp, bp), dot(cp, cp)});
    return d;
}

}  // namespace

float point_triangle_distance(const Vec3f& p, const Vec3f* v) { return std::sqrt(distance2(p, v)); }

namespace {

// The squared distances from the 8 corners (cx, cy, cz) of a box to the triangle v, all
// at once and without branches, which the compiler runs in SIMD (this file builds with
// -fno-trapping-math so that it may): the distance to the plane where a corner lies over
// the triangle (its three edge tests pass), else to the nearest edge as a segment. The
// same distances as distance2, up to rounding, for the leaf's first triangle, which
// every corner is measured against.
void corner_distances2(const float (&cx)[8], const float (&cy)[8], const float (&cz)[8], const Vec3f* v,
                       float (&out)[8]) {
    const Vec3f n = cross(v[1] - v[0], v[2] - v[0]);
    const float nn = dot(n, n);
    const float inv_nn = nn > 0 ? 1.0f / nn : 0.0f;
    float best[8], over[8], h[8];
    for (int c = 0; c < 8; ++c) {
        best[c] = std::numeric_limits<float>::max();
        over[c] = nn > 0 ? 1.0f : 0.0f;
        h[c] = (cx[c] - v[0].x) * n.x + (cy[c] - v[0].y) * n.y + (cz[c] - v[0].z) * n.z;
    }
    for (int i = 0; i < 3; ++i) {
        const Vec3f a = v[i], e = v[i == 2 ? 0 : i + 1] - v[i];
        const Vec3f m = cross(n, e);  // points into the triangle from edge i, in its plane
        const float ee = dot(e, e);
        const float inv_ee = ee > 0 ? 1.0f / ee : 0.0f;
        for (int c = 0; c < 8; ++c) {
            const float px = cx[c] - a.x, py = cy[c] - a.y, pz = cz[c] - a.z;
            over[c] = px * m.x + py * m.y + pz * m.z >= 0 ? over[c] : 0.0f;
            const float t = std::min(std::max((px * e.x + py * e.y + pz * e.z) * inv_ee, 0.0f), 1.0f);
            const float qx = px - t * e.x, qy = py - t * e.y, qz = pz - t * e.z;
            best[c] = std::min(best[c], qx * qx + qy * qy + qz * qz);
        }
    }
    for (int c = 0; c < 8; ++c) out[c] = over[c] > 0 ? h[c] * h[c] * inv_nn : best[c];
}

}  // namespace

float leaf_error(const TriangleSource& src, const std::uint32_t* tris, std::uint32_t count, const Box3f& cell,
                 float enough) {
    if (count == 0) return kInf;
    Vec3f corner[8];
    float cx[8], cy[8], cz[8];
    float magnitude = 0;
    for (int c = 0; c < 8; ++c) {
        corner[c] = Vec3f((c & 1) ? cell.hi.x : cell.lo.x, (c & 2) ? cell.hi.y : cell.lo.y,
                          (c & 4) ? cell.hi.z : cell.lo.z);
        cx[c] = corner[c].x;
        cy[c] = corner[c].y;
        cz[c] = corner[c].z;
        for (int a = 0; a < 3; ++a) magnitude = std::max(magnitude, std::abs(corner[c][a]));
    }
    const Vec3f centre = (cell.lo + cell.hi) * 0.5f, half = (cell.hi - cell.lo) * 0.5f;
    // The largest triangle first: it usually bounds the cell best, often well enough. A
    // later one is passed over when even its plane lies further from some corner (the
    // corners' largest distance to a plane, in closed form, bounds their largest distance
    // to the triangle from below), else dropped at its first corner that is no better,
    // starting at the corner that decided the best so far. Any triangle's bound is an
    // upper bound: trying fewer only loosens it.
    std::uint32_t first = 0;
    for (std::uint32_t i = 1; i < count; ++i) {
        if (src.facets[tris[i]].area > src.facets[tris[first]].area) first = i;
    }
    const float enough2 = enough > 0 ? enough * enough : 0.0f;
    // At most two triangles are tried in full: the 10^7 plant's LOD nodes under their
    // radius were 720,735 with every triangle tried and 521,257 with two, for overviews
    // within 3 % of its working set and the same images, in under half the time.
    constexpr std::uint32_t kTried = 2;
    std::uint32_t tried = 0;
    float best2 = kInf;
    int far = 0;
    for (std::uint32_t j = 0; j < count && best2 > enough2 && tried < kTried; ++j) {
        const std::uint32_t i = j == 0 ? first : (j == first ? 0 : j);
        const Vec3f* v = src.corners(tris[i]);
        const Facet& f = src.facets[tris[i]];
        if (j > 0 && f.area > 0) {
            const Vec3f& n = f.normal;
            const float plane = std::abs(dot(n, centre - v[0])) + std::abs(n.x) * half.x + std::abs(n.y) * half.y +
                                std::abs(n.z) * half.z;
            if (plane * plane >= best2) continue;
        }
        ++tried;
        float worst2 = 0;
        int at = far;
        if (j == 0) {
            float d2[8];
            corner_distances2(cx, cy, cz, v, d2);
            for (int c = 0; c < 8; ++c) {
                if (d2[c] > worst2) {
                    worst2 = d2[c];
                    at = c;
                }
            }
        }
        for (int k = 0; j > 0 && k < 8 && worst2 < best2; ++k) {
            const int c = (far + k) & 7;
            const float d2 = distance2(corner[c], v);
            if (d2 > worst2) {
                worst2 = d2;
                at = c;
            }
        }
        if (worst2 < best2) {
            best2 = worst2;
            far = at;
        }
    }
    // Rounding in f32: a relative and an absolute margin (coordinates of this size are
    // good to about 2^-23 of it).
    return std::sqrt(best2) * (1.0f + 1e-5f) + magnitude * 1e-6f;
}

float inner_error(const Box3f& cell, int axis, float split, float left, float right) {
    const bool has_l = left < kInf, has_r = right < kInf;
    if (!has_l && !has_r) return kInf;
    if (!has_l) return (split - cell.lo[axis]) + right;
    if (!has_r) return (cell.hi[axis] - split) + left;
    return std::max(left, right);
}

std::vector<float> kd_errors(const KdTree& tree, const TriangleSource& src, const Box3f& cell, float floor,
                             unsigned lanes) {
    std::vector<float> out(tree.nodes.size(), kInf);
    if (tree.nodes.empty()) return out;
    // The nodes above depth kTop, in preorder, and the subtrees below them as jobs.
    constexpr int kTop = 8;
    std::vector<Place> top, jobs, stack{{0, cell, 0, 0.0f}};
    while (!stack.empty()) {
        const Place p = stack.back();
        stack.pop_back();
        const KdNode& k = tree.nodes[p.node];
        if (k.is_leaf() || p.depth == kTop) {
            jobs.push_back(p);
            continue;
        }
        top.push_back(p);
        if (!k.right_empty()) stack.push_back(p.child(k, 1, k.right_offset()));
        if (!k.left_empty()) stack.push_back(p.child(k, 0, k.right_offset()));
    }
    ThreadPool::global().parallel_for(
        jobs.size(), [&](std::size_t j, unsigned) { SubtreeErrors(tree, src, floor, out.data()).run(jobs[j]); },
        lanes);
    for (auto it = top.rbegin(); it != top.rend(); ++it) {
        const KdNode& k = tree.nodes[it->node];
        const float l = k.left_empty() ? kInf : out[it->node + 1];
        const float r = k.right_empty() ? kInf : out[it->node + k.right_offset()];
        out[it->node] = inner_error(it->cell, k.axis(), k.split(), l, r);
    }
    return out;
}

}  // namespace vastray::writer
