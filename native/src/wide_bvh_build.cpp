// Top-down binned-SAH build of the 8-wide BVH (wide_bvh.h), in the manner of Embree's
// BVHN builder: a node starts as one child holding all its triangles, and the child of
// largest surface area is split in two by the SAH until there are eight or every child
// is small enough to be a leaf. The subtrees of the root's grandchildren are built in
// parallel, each subtree into its own array, and spliced after.
#include <algorithm>
#include <array>
#include <chrono>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <utility>
#include <vector>

#include <emmintrin.h>

#include "vastray/thread_pool.h"
#include "vastray/wide_bvh.h"

namespace vastray {
namespace {

constexpr int kBins = 16;
// Leaves of at most 4 triangles, one WideQuad, tested in one SSE pass. With the scalar
// test of one triangle after the other, 2 had been best (AO rays 1.06-1.15x against 4);
// with the quads 4 measured 1.10-1.12x of 2 and 8 no better than 4 (docs/native-core.md).
constexpr std::uint32_t kLeafMax = WideQuad::kLanes;
// Halving from this depth on adds at most log2(2^28) / 3 < 10 levels: a walk's stack
// (WideWalk, 7 entries a level) then holds every tree.
constexpr int kHalveDepth = 48;
// The subtrees from this depth (the root's grandchildren) are built in parallel.
constexpr int kParallelDepth = 2;
constexpr float kInf = std::numeric_limits<float>::infinity();

struct Range {
    std::uint32_t begin = 0, end = 0;
    Box3f bounds;     // of the triangles
    Box3f centroids;  // of their centroids
    std::uint32_t count() const { return end - begin; }
};

float area(const Box3f& b) { return b.empty() ? 0.0f : b.half_area(); }

// A box as two SSE vectors (x, y, z in lanes 0-2; lane 3 unused), so that extending it
// takes two instructions. _mm_min_ps(p, lo) and _mm_max_ps(p, hi) keep the old bound on
// a tie, as Box3f::extend's std::min / std::max do: the bounds are the same bits.
struct BoxV {
    __m128 lo = _mm_set1_ps(std::numeric_limits<float>::infinity());
    __m128 hi = _mm_set1_ps(-std::numeric_limits<float>::infinity());

    void extend(__m128 p_lo, __m128 p_hi) {
        lo = _mm_min_ps(p_lo, lo);
        hi = _mm_max_ps(p_hi, hi);
    }
    Box3f box() const {
        alignas(16) float l[4], h[4];
        _mm_store_ps(l, lo);
        _mm_store_ps(h, hi);
        return Box3f{{l[0], l[1], l[2]}, {h[0], h[1], h[2]}};
    }
};

// Box3f's six floats as two vectors (lane 3 holds a neighbouring coordinate, unused),
// read within the box's own 24 bytes.
inline void load_box(const Box3f& b, __m128& lo, __m128& hi) {
    lo = _mm_loadu_ps(&b.lo.x);  // lo.x lo.y lo.z hi.x
    const __m128 tail = _mm_loadu_ps(&b.lo.z);  // lo.z hi.x hi.y hi.z
    hi = _mm_shuffle_ps(tail, tail, _MM_SHUFFLE(0, 3, 2, 1));
}

class Builder {
public:
    Builder(const std::vector<Box3f>& boxes, const std::vector<Vec3f>& centres, std::vector<std::uint32_t>& order)
        : boxes_(boxes), centres_(centres), order_(order) {}

    Range range(std::uint32_t begin, std::uint32_t end) const {
        BoxV bounds, centroids;
        const __m128 half = _mm_set1_ps(0.5f);
        for (std::uint32_t i = begin; i < end; ++i) {
            __m128 lo, hi;
            load_box(boxes_[order_[i]], lo, hi);
            const __m128 c = _mm_mul_ps(_mm_add_ps(lo, hi), half);  // = centres_[t], bit for bit
            bounds.extend(lo, hi);
            centroids.extend(c, c);
        }
        return Range{begin, end, bounds.box(), centroids.box()};
    }

    // Splits `r` in two along the cheapest of kBins planes per axis; where the centroids
    // coincide (no plane separates them), or `halve`, in the middle of the list.
    std::pair<Range, Range> split(const Range& r, bool halve) const {
        if (halve) return {range(r.begin, r.begin + r.count() / 2), range(r.begin + r.count() / 2, r.end)};
        const Vec3f lo = r.centroids.lo, ext = r.centroids.extent();
        int best_axis = -1, best_plane = 0;
        float best_cost = kInf;
        std::array<std::array<std::uint32_t, kBins>, 3> bin_counts{};
        float scale[3];
        for (int a = 0; a < 3; ++a) scale[a] = ext[a] > 0 ? kBins * (1.0f - 1e-6f) / ext[a] : 0.0f;
        // The three axes' bins of a triangle at once: bin_of's float arithmetic and
        // truncation lane by lane (cvttps gives what static_cast<int> gives, INT_MIN out of
        // range), then its clamp to [0, kBins) on the integers. Same bins, same bounds.
        std::array<std::array<BoxV, kBins>, 3> bins;
        {
            const __m128 v_lo = _mm_setr_ps(lo.x, lo.y, lo.z, 0.0f);
            const __m128 v_scale = _mm_setr_ps(scale[0], scale[1], scale[2], 0.0f);
            const __m128 half = _mm_set1_ps(0.5f);
            const __m128i zero = _mm_setzero_si128(), top = _mm_set1_epi32(kBins - 1);
            for (std::uint32_t i = r.begin; i < r.end; ++i) {
                __m128 b_lo, b_hi;
                load_box(boxes_[order_[i]], b_lo, b_hi);
                const __m128 c = _mm_mul_ps(_mm_add_ps(b_lo, b_hi), half);
                __m128i b = _mm_cvttps_epi32(_mm_mul_ps(_mm_sub_ps(c, v_lo), v_scale));
                b = _mm_and_si128(b, _mm_cmpgt_epi32(b, zero));
                const __m128i over = _mm_cmpgt_epi32(b, top);
                b = _mm_or_si128(_mm_andnot_si128(over, b), _mm_and_si128(over, top));
                alignas(16) std::int32_t bin[4];
                _mm_store_si128(reinterpret_cast<__m128i*>(bin), b);
                for (int a = 0; a < 3; ++a) {
                    bins[a][bin[a]].extend(b_lo, b_hi);
                    ++bin_counts[a][bin[a]];
                }
            }
        }
        std::array<std::array<Box3f, kBins>, 3> bin_boxes;
        for (int a = 0; a < 3; ++a) {
            for (int b = 0; b < kBins; ++b) bin_boxes[a][b] = bins[a][b].box();
        }
        for (int a = 0; a < 3; ++a) {
            if (scale[a] == 0.0f) continue;
            // Sweep from the right to know each plane's right-hand cost, then from the left.
            float right_cost[kBins];
            Box3f acc;
            std::uint32_t n = 0;
            for (int b = kBins - 1; b > 0; --b) {
                acc.extend(bin_boxes[a][b]);
                n += bin_counts[a][b];
                right_cost[b] = area(acc) * static_cast<float>(n);
            }
            acc = Box3f{};
            n = 0;
            for (int b = 0; b < kBins - 1; ++b) {
                acc.extend(bin_boxes[a][b]);
                n += bin_counts[a][b];
                const float cost = area(acc) * static_cast<float>(n) + right_cost[b + 1];
                if (n > 0 && n < r.count() && cost < best_cost) {
                    best_cost = cost;
                    best_axis = a;
                    best_plane = b + 1;
                }
            }
        }
        std::uint32_t mid;
        if (best_axis < 0) {
            mid = r.begin + r.count() / 2;
        } else {
            const auto first = order_.begin() + r.begin, last = order_.begin() + r.end;
            const float l = lo[best_axis], s = scale[best_axis];
            mid = r.begin + static_cast<std::uint32_t>(
                                std::partition(first, last,
                                               [&](std::uint32_t t) {
                                                   return bin_of(centres_[t][best_axis], l, s) < best_plane;
                                               }) -
                                first);
        }
        return {range(r.begin, mid), range(mid, r.end)};
    }

    // The children of a node over `r`: split the largest until 8 or all are leaves.
    // Below kHalveDepth every split halves its list, so no tree is deeper than the
    // traversal stack allows, whatever the SAH would have made of the triangles.
    std::vector<Range> children(const Range& r, int depth) const {
        std::vector<Range> kids{r};
        while (kids.size() < WideNode::kWidth) {
            int pick = -1;
            float pick_area = -1.0f;
            for (std::size_t k = 0; k < kids.size(); ++k) {
                // (Every child too large for a leaf is a candidate, whatever its area, so
                // a node always gets at least two children.)
                const float a = area(kids[k].bounds);
                const float key = a >= 0.0f ? a : kInf;
                if (kids[k].count() > kLeafMax && (pick < 0 || key > pick_area)) {
                    pick = static_cast<int>(k);
                    pick_area = key;
                }
            }
            if (pick < 0) break;
            auto [a, b] = split(kids[static_cast<std::size_t>(pick)], depth >= kHalveDepth);
            kids[static_cast<std::size_t>(pick)] = a;
            kids.push_back(b);
        }
        return kids;
    }

    static std::uint32_t leaf_code(const Range& r) {
        return WideNode::kLeafBit | r.begin << WideNode::kCountBits | (r.count() - 1);
    }

    // A subtree left for later (and for another thread): its range, and the slot of its
    // parent node that will hold its root.
    struct Deferred {
        Range range;
        std::uint32_t node;
        int slot;
    };

    // Builds the subtree over `r` into `out`; returns its child code (node indices local
    // to `out`). With `defer`, the subtrees at kParallelDepth are not built but listed
    // there, their parents' slots left to fill.
    std::uint32_t build(const Range& r, int depth, std::vector<WideNode>& out,
                        std::vector<Deferred>* defer = nullptr) const {
        if (r.count() <= kLeafMax) return leaf_code(r);
        const std::uint32_t index = static_cast<std::uint32_t>(out.size());
        out.emplace_back();
        const std::vector<Range> kids = children(r, depth);
        WideNode node = empty_node();
        for (std::size_t k = 0; k < kids.size(); ++k) {
            set_box(node, static_cast<int>(k), kids[k].bounds);
            if (defer != nullptr && depth + 1 == kParallelDepth && kids[k].count() > kLeafMax) {
                defer->push_back({kids[k], index, static_cast<int>(k)});
            } else {
                node.child[k] = build(kids[k], depth + 1, out, defer);
            }
        }
        out[index] = node;
        return index;
    }

    static WideNode empty_node() {
        WideNode n;
        for (int k = 0; k < WideNode::kWidth; ++k) {
            n.lo_x[k] = n.lo_y[k] = n.lo_z[k] = kInf;
            n.hi_x[k] = n.hi_y[k] = n.hi_z[k] = -kInf;
            n.child[k] = 0;
        }
        return n;
    }

    static void set_box(WideNode& n, int k, const Box3f& b) {
        n.lo_x[k] = b.lo.x;
        n.lo_y[k] = b.lo.y;
        n.lo_z[k] = b.lo.z;
        n.hi_x[k] = b.hi.x;
        n.hi_y[k] = b.hi.y;
        n.hi_z[k] = b.hi.z;
    }

private:
    static int bin_of(float c, float lo, float scale) {
        const int b = static_cast<int>((c - lo) * scale);
        return std::clamp(b, 0, kBins - 1);
    }

    const std::vector<Box3f>& boxes_;
    const std::vector<Vec3f>& centres_;
    std::vector<std::uint32_t>& order_;
};

// Gives every leaf its run of quads, in the order of the leaves' triangle ranges (the
// build's depth-first order), and rewrites its code to point at them.
void pack_leaves(WideBvh& bvh, const std::vector<std::uint32_t>& order, const Vec3f* tri_vertices,
                 unsigned threads) {
    const auto n = static_cast<std::uint32_t>(order.size());
    // The triangle count of the leaf that begins at each position of `order` (0: none).
    std::vector<std::uint8_t> count_at(n, 0);
    ThreadPool& pool = ThreadPool::global();
    constexpr std::size_t kNodeChunk = 1 << 12;
    const std::size_t chunks = (bvh.nodes.size() + kNodeChunk - 1) / kNodeChunk;
    const auto for_leaf_codes = [&](auto&& visit) {
        pool.parallel_for(chunks, [&](std::size_t c, unsigned) {
            const std::size_t end = std::min(bvh.nodes.size(), (c + 1) * kNodeChunk);
            for (std::size_t i = c * kNodeChunk; i < end; ++i) {
                WideNode& node = bvh.nodes[i];
                for (int k = 0; k < WideNode::kWidth; ++k) {
                    if (node.lo_x[k] <= node.hi_x[k] && WideNode::is_leaf(node.child[k])) visit(node.child[k]);
                }
            }
        }, threads);
    };
    for_leaf_codes([&](std::uint32_t code) {
        count_at[WideNode::leaf_first(code)] = static_cast<std::uint8_t>(WideNode::leaf_count(code));
    });
    std::vector<std::uint32_t> quad_at(n, 0);
    std::uint32_t quads = 0;
    for (std::uint32_t i = 0; i < n; ++i) {
        quad_at[i] = quads;
        quads += WideQuad::count_for(count_at[i]);
    }
    bvh.quads.resize(quads);
    for_leaf_codes([&](std::uint32_t& code) {
        const std::uint32_t begin = WideNode::leaf_first(code), count = WideNode::leaf_count(code);
        const std::uint32_t first = quad_at[begin];
        for (std::uint32_t q = 0; q < WideQuad::count_for(count); ++q) {
            WideQuad& quad = bvh.quads[first + q];
            for (int lane = 0; lane < WideQuad::kLanes; ++lane) {
                const std::uint32_t i = q * WideQuad::kLanes + static_cast<std::uint32_t>(lane);
                const std::uint32_t t = order[begin + (i < count ? i : 0)];
                for (int k = 0; k < 3; ++k) {
                    const Vec3f& p = tri_vertices[3 * static_cast<std::size_t>(t) + static_cast<std::size_t>(k)];
                    quad.v[k][0][lane] = p.x;
                    quad.v[k][1][lane] = p.y;
                    quad.v[k][2][lane] = p.z;
                }
                quad.prim[lane] = t;
            }
        }
        code = WideNode::kLeafBit | first << WideNode::kCountBits | (count - 1);
    });
}

}  // namespace

WideBvh build_wide_bvh(const Vec3f* tri_vertices, std::size_t triangle_count, unsigned threads) {
    const auto start = std::chrono::steady_clock::now();
    if (triangle_count > WideNode::kMaxFirst) throw std::length_error("too many triangles for the wide BVH");
    const auto total = static_cast<std::uint32_t>(triangle_count);
    std::vector<Box3f> boxes(total);
    std::vector<Vec3f> centres(total);
    std::vector<std::uint8_t> kept(total);
    ThreadPool& pool = ThreadPool::global();
    constexpr std::size_t kChunk = 1 << 16;
    pool.parallel_for((total + kChunk - 1) / kChunk, [&](std::size_t c, unsigned) {
        const std::size_t end = std::min<std::size_t>(total, (c + 1) * kChunk);
        for (std::size_t t = c * kChunk; t < end; ++t) {
            const Vec3f* v = tri_vertices + 3 * t;
            kept[t] = has_area(v[0], v[1], v[2]);
            Box3f b;
            for (int k = 0; k < 3; ++k) b.extend(v[k]);
            boxes[t] = b;
            centres[t] = (b.lo + b.hi) * 0.5f;
        }
    }, threads);
    std::vector<std::uint32_t> order;
    order.reserve(total);
    for (std::uint32_t t = 0; t < total; ++t) {
        if (kept[t]) order.push_back(t);
    }
    const auto n = static_cast<std::uint32_t>(order.size());
    Builder builder(boxes, centres, order);
    WideBvh bvh;
    const Range all = builder.range(0, n);
    if (n <= kLeafMax) {
        // Too few for a node: the walk starts at a node, so the root holds one leaf (or
        // nothing at all).
        WideNode root = Builder::empty_node();
        if (n > 0) {
            Builder::set_box(root, 0, all.bounds);
            root.child[0] = Builder::leaf_code(all);
        }
        bvh.nodes.push_back(root);
    } else {
        // The root and its children serially; the grandchildren's subtrees in parallel.
        std::vector<WideNode> top;
        std::vector<Builder::Deferred> tasks;
        builder.build(all, 0, top, &tasks);
        std::vector<std::vector<WideNode>> parts(tasks.size());
        std::vector<std::uint32_t> roots(tasks.size());
        pool.parallel_for(tasks.size(), [&](std::size_t i, unsigned) {
            roots[i] = builder.build(tasks[i].range, kParallelDepth, parts[i]);
        }, threads);
        std::size_t node_count = top.size();
        for (const auto& p : parts) node_count += p.size();
        bvh.nodes.reserve(node_count);
        bvh.nodes.assign(top.begin(), top.end());
        for (std::size_t i = 0; i < tasks.size(); ++i) {
            const auto base = static_cast<std::uint32_t>(bvh.nodes.size());
            for (WideNode node : parts[i]) {
                for (std::uint32_t& c : node.child) {
                    if (!WideNode::is_leaf(c) && c != 0) c += base;
                }
                bvh.nodes.push_back(node);
            }
            bvh.nodes[tasks[i].node].child[tasks[i].slot] = roots[i] + base;
        }
    }
    pack_leaves(bvh, order, tri_vertices, threads);
    // Shape statistics, by a walk from the root.
    std::vector<std::pair<std::uint32_t, int>> todo{{0u, 1}};
    while (!todo.empty()) {
        const auto [index, depth] = todo.back();
        todo.pop_back();
        bvh.max_depth = std::max(bvh.max_depth, depth);
        const WideNode& node = bvh.nodes[index];
        for (int k = 0; k < WideNode::kWidth; ++k) {
            if (node.lo_x[k] > node.hi_x[k]) continue;  // unused slot
            if (WideNode::is_leaf(node.child[k])) {
                ++bvh.leaves;
            } else {
                todo.push_back({node.child[k], depth + 1});
            }
        }
    }
    bvh.build_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    return bvh;
}

}  // namespace vastray
