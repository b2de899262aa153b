// Binned-SAH kd-tree construction with empty-space cutting and split clipping.
//
// Triangles that straddle a split plane are clipped at it so the references below
// carry tight boxes (close to "perfect splits"); that keeps duplicated references
// from inflating deeper levels. Every box that decides membership is
// widened by a few ulps first: a reference may be kept where it only touches, but a
// triangle is never dropped from a cell it overlaps, which is what watertight
// traversal needs.
#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <deque>
#include <exception>
#include <memory>
#include <mutex>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <new>
#include <stdexcept>
#include <type_traits>
#include <thread>
#include <utility>

#include <emmintrin.h>

#include "vastray/format.h"
#include "vastray/kdtree.h"
#include "vastray/thread_pool.h"

namespace vastray {
namespace {

struct PrimRef {
    Box3f box;  // the triangle clipped to the current cell, slightly widened
    std::uint32_t id;
};

struct Output {
    explicit Output(bool huge_pages = true)
        : nodes(HugePageAllocator<KdNode>(huge_pages)), tri_ids(HugePageAllocator<std::uint32_t>(huge_pages)) {}

    HugeVector<KdNode> nodes;
    HugeVector<std::uint32_t> tri_ids;
    KdBuildStats stats;
    double sah_area_sum = 0;  // sum over nodes of area-weighted costs, normalised at the end
};

// Widen a box by a relative epsilon so float rounding in clipping never shrinks a
// triangle's footprint below the cell it really touches.
Box3f widen(const Box3f& b) {
    Box3f r = b;
    for (int a = 0; a < 3; ++a) {
        const float m = std::max(std::abs(b.lo[a]), std::abs(b.hi[a]));
        const float eps = m * 4.0f * std::numeric_limits<float>::epsilon() +
                          std::numeric_limits<float>::min();
        r.lo[a] = b.lo[a] - eps;
        r.hi[a] = b.hi[a] + eps;
    }
    return r;
}

// Bounds of the parts of a triangle on each side of an axis-aligned plane (side 0:
// coordinate <= split, side 1: >= split), in double. Clipping against the one split
// plane and intersecting with the reference's current box is nearly as tight as a full
// polygon clip against the child cell, at a fraction of the cost: long thin triangles
// (pipes, cables) straddle many planes, so this runs at every level. Both sides in one
// pass: an edge's crossing point is the same for both (same endpoints, same order), and
// each side's box takes its points in the order a pass of its own would.
void clip_to_half_spaces(const Vec3f& a, const Vec3f& b, const Vec3f& c, int axis, float split, Box3f& below,
                         Box3f& above) {
    const Vec3d p[3] = {Vec3d(a), Vec3d(b), Vec3d(c)};
    const double plane = split;
    below = Box3f{};
    above = Box3f{};
    for (int i = 0; i < 3; ++i) {
        const Vec3d& q0 = p[i];
        const Vec3d& q1 = p[(i + 1) % 3];
        const bool lo0 = q0[axis] <= plane, lo1 = q1[axis] <= plane;
        const bool hi0 = q0[axis] >= plane, hi1 = q1[axis] >= plane;
        const bool cross_lo = lo0 != lo1, cross_hi = hi0 != hi1;
        Vec3f x;
        if (cross_lo || cross_hi) {
            const double s = (plane - q0[axis]) / (q1[axis] - q0[axis]);
            Vec3d xd = q0 + (q1 - q0) * s;
            xd[axis] = plane;
            x = Vec3f(xd);
        }
        if (lo0) below.extend(Vec3f(q0));
        if (cross_lo) below.extend(x);
        if (hi0) above.extend(Vec3f(q0));
        if (cross_hi) above.extend(x);
    }
}

// Bounds of the part of a triangle inside a box (Sutherland-Hodgman in double), or an
// empty box when the triangle misses it. An out-of-core subtree receives every triangle
// whose bounding box touches its cell; this gives each one its tight footprint there.
Box3f clip_to_box(const Vec3f& a, const Vec3f& b, const Vec3f& c, const Box3f& box) {
    Vec3d poly[9] = {Vec3d(a), Vec3d(b), Vec3d(c)}, next[9];
    int n = 3;
    for (int axis = 0; axis < 3 && n > 0; ++axis) {
        for (int side = 0; side < 2 && n > 0; ++side) {
            const double plane = side == 0 ? box.lo[axis] : box.hi[axis];
            auto inside = [&](const Vec3d& q) { return side == 0 ? q[axis] >= plane : q[axis] <= plane; };
            int m = 0;
            for (int i = 0; i < n; ++i) {
                const Vec3d& q0 = poly[i];
                const Vec3d& q1 = poly[(i + 1) % n];
                if (inside(q0)) next[m++] = q0;
                if (inside(q0) != inside(q1) && m < 9) {
                    const double s = (plane - q0[axis]) / (q1[axis] - q0[axis]);
                    Vec3d x = q0 + (q1 - q0) * s;
                    x[axis] = plane;
                    next[m++] = x;
                }
            }
            n = std::min(m, 9);
            std::copy(next, next + n, poly);
        }
    }
    Box3f r;
    for (int i = 0; i < n; ++i) r.extend(Vec3f(poly[i]));
    return r;
}

// Exact triangle/box overlap by separating axes (Akenine-Möller 2001), in double: the
// box's three axes, the triangle's normal and the nine edge-axis cross products.
bool triangle_overlaps_box(const Vec3f& fa, const Vec3f& fb, const Vec3f& fc, const Vec3d& lo, const Vec3d& hi) {
    const Vec3d centre = (lo + hi) * 0.5, half = (hi - lo) * 0.5;
    const Vec3d v[3] = {Vec3d(fa) - centre, Vec3d(fb) - centre, Vec3d(fc) - centre};
    for (int a = 0; a < 3; ++a) {
        const double mn = std::min({v[0][a], v[1][a], v[2][a]}), mx = std::max({v[0][a], v[1][a], v[2][a]});
        if (mn > half[a] || mx < -half[a]) return false;
    }
    const Vec3d e[3] = {v[1] - v[0], v[2] - v[1], v[0] - v[2]};
    auto separated = [&](const Vec3d& axis) {
        const double p0 = dot(v[0], axis), p1 = dot(v[1], axis), p2 = dot(v[2], axis);
        const double r = half.x * std::abs(axis.x) + half.y * std::abs(axis.y) + half.z * std::abs(axis.z);
        return std::min({p0, p1, p2}) > r || std::max({p0, p1, p2}) < -r;
    };
    if (separated(cross(e[0], e[1]))) return false;
    for (const Vec3d& edge : e) {
        for (int a = 0; a < 3; ++a) {
            Vec3d unit;
            unit[a] = 1;
            if (separated(cross(edge, unit))) return false;
        }
    }
    return true;
}

// The references of the nodes on the current path, in one growable buffer per thread.
// A node's references are a range [first, first + n) with free space above it: its
// partition writes the left child's references above the range, compacts the right
// child's in place (each reference read gives at most one to the right, so writes never
// overtake reads) and moves the left child's down behind them. The left subtree is then
// built above the right child's range, which it never touches. No node allocates.
// A box's corners in SSE registers (lane 3: 0), built from the components rather than
// loaded as a vector: a box just computed lies in memory as scalar stores, and a
// 16-byte load across them waits for a failed store forward.
inline __m128 load_lo(const Box3f& b) { return _mm_setr_ps(b.lo.x, b.lo.y, b.lo.z, 0.0f); }
inline __m128 load_hi(const Box3f& b) { return _mm_setr_ps(b.hi.x, b.hi.y, b.hi.z, 0.0f); }
inline Box3f to_box(__m128 lo, __m128 hi) {
    alignas(16) float l[4], h[4];
    _mm_store_ps(l, lo);
    _mm_store_ps(h, hi);
    Box3f b;
    b.lo = {l[0], l[1], l[2]};
    b.hi = {h[0], h[1], h[2]};
    return b;
}

class RefStack {
public:
    RefStack() = default;
    RefStack(const RefStack&) = delete;
    RefStack& operator=(const RefStack&) = delete;
    ~RefStack() { std::free(refs_); }

    PrimRef* data() { return refs_; }
    // Makes room for references up to index `top`; may move the buffer. The memory is
    // not initialised: untouched room costs address space, not resident pages, and a
    // large block grows by remapping rather than copying. Only the owning thread calls it.
    void reserve(std::size_t top) {
        if (top <= capacity_) return;
        const std::size_t want = std::max(top, capacity_ + capacity_ / 2);
        std::lock_guard<std::mutex> lock(move_);
        void* grown = std::realloc(static_cast<void*>(refs_), want * sizeof(PrimRef));
        if (grown == nullptr) throw std::bad_alloc();
        refs_ = static_cast<PrimRef*>(grown);
        capacity_ = want;
    }
    // Copies references [first, first + n) for another thread, which the owner does not
    // touch meanwhile; the lock keeps the owner from moving the buffer under the copy.
    void copy_out(std::size_t first, std::size_t n, PrimRef* to) {
        std::lock_guard<std::mutex> lock(move_);
        std::memcpy(to, refs_ + first, n * sizeof(PrimRef));
    }

private:
    PrimRef* refs_ = nullptr;  // PrimRef is trivially copyable: realloc may move it
    std::size_t capacity_ = 0;
    std::mutex move_;
};
static_assert(std::is_trivially_copyable_v<PrimRef>, "references are moved by realloc and memmove");

// Puts boxes into the bins of one cell (the binned SAH's input: per axis, how many
// boxes start and end in each slice): bin = (x - lo) * bins / extent, clamped to
// 0 ... bins - 1 in float before it is truncated (which is what a scalar static_cast of
// the clamped float gives). Lane 3 of a corner is whatever follows it in memory; it is
// scaled by 0 and clamped, and its bin is never counted.
class Binner {
public:
    Binner(const Box3f& cell, int bins) : bins_(bins) {
        float scale[3];
        for (int a = 0; a < 3; ++a) {
            const float ext = cell.hi[a] - cell.lo[a];
            scale[a] = ext > 0 ? static_cast<float>(bins) / ext : 0.0f;
        }
        lo_ = _mm_setr_ps(cell.lo.x, cell.lo.y, cell.lo.z, 0.0f);
        scale_ = _mm_setr_ps(scale[0], scale[1], scale[2], 0.0f);
        top_ = _mm_set1_ps(static_cast<float>(bins - 1));
        base_ = _mm_setr_epi32(0, bins, 2 * bins, 0);
    }
    int bins() const { return bins_; }
    void add(__m128 lo, __m128 hi, std::uint32_t* starts, std::uint32_t* ends) const {
        alignas(16) std::int32_t s[4], e[4];
        _mm_store_si128(reinterpret_cast<__m128i*>(s), _mm_add_epi32(_mm_cvttps_epi32(clamp(lo)), base_));
        _mm_store_si128(reinterpret_cast<__m128i*>(e), _mm_add_epi32(_mm_cvttps_epi32(clamp(hi)), base_));
        starts[s[0]]++;
        starts[s[1]]++;
        starts[s[2]]++;
        ends[e[0]]++;
        ends[e[1]]++;
        ends[e[2]]++;
    }

private:
    __m128 clamp(__m128 x) const {
        return _mm_min_ps(_mm_max_ps(_mm_mul_ps(_mm_sub_ps(x, lo_), scale_), _mm_setzero_ps()), top_);
    }
    int bins_;
    __m128 lo_, scale_, top_;
    __m128i base_;
};

// Fork-join over subtrees: a split with two big children offers the right one as a task
// and builds the left one itself. An idle helper takes the oldest task on offer (the
// biggest: the one nearest the root) and builds it into an output of its own. Back from
// the left child, the owner builds the right one itself if nobody took it, or waits for
// it and splices the helper's output after the left child's. While it waits, it builds
// tasks on offer itself (the helper's own right children), so neither thread idles
// while the other has work to give. Who builds what changes nothing in the tree: the
// nodes end up in the same preorder either way.
struct Task {
    RefStack* stack = nullptr;  // the owner's: the child's references lie there, untouched meanwhile
    std::size_t first = 0, n = 0;
    Box3f cell, used;
    int depth = 0, bad = 0;
    enum State { Offered, Taken, Reclaimed } state = Offered;  // guarded by Tasks::mutex_
    bool done = false;
    std::exception_ptr error;
    Output out;
};

class Tasks {
public:
    void offer(Task* t) {
        {
            std::lock_guard<std::mutex> lock(mutex_);
            offered_.push_back(t);
            on_offer_.store(offered_.size(), std::memory_order_relaxed);
        }
        changed_.notify_all();  // an idle helper, or an owner waiting for its own task
    }
    // The owner takes its task back; false when a helper has it.
    bool reclaim(Task* t) {
        std::lock_guard<std::mutex> lock(mutex_);
        if (t->state != Task::Offered) return false;
        t->state = Task::Reclaimed;
        offered_.erase(std::find(offered_.begin(), offered_.end(), t));
        on_offer_.store(offered_.size(), std::memory_order_relaxed);
        return true;
    }
    void wait(Task* t) {
        std::unique_lock<std::mutex> lock(mutex_);
        changed_.wait(lock, [t] { return t->done; });
    }
    // Until `t` (taken by another thread) is done: a task on offer for the caller to
    // build meanwhile. Null once `t` is done.
    Task* wait_or_take(Task* t) {
        std::unique_lock<std::mutex> lock(mutex_);
        changed_.wait(lock, [this, t] { return t->done || !offered_.empty(); });
        return t->done ? nullptr : pop();
    }
    // A helper's next task, or null once the build is over.
    Task* take() {
        std::unique_lock<std::mutex> lock(mutex_);
        changed_.wait(lock, [this] { return over_ || !offered_.empty(); });
        return offered_.empty() ? nullptr : pop();
    }
    void complete(Task* t) {
        {
            std::lock_guard<std::mutex> lock(mutex_);
            t->done = true;
        }
        changed_.notify_all();
    }
    void end() {
        {
            std::lock_guard<std::mutex> lock(mutex_);
            over_ = true;
        }
        changed_.notify_all();
    }
    // Subtrees waiting for a thread (a hint: it changes as soon as it is read).
    std::size_t on_offer() const { return on_offer_.load(std::memory_order_relaxed); }

private:
    Task* pop() {  // the oldest task on offer: the biggest
        Task* t = offered_.front();
        offered_.pop_front();
        on_offer_.store(offered_.size(), std::memory_order_relaxed);
        t->state = Task::Taken;
        return t;
    }
    std::mutex mutex_;
    std::condition_variable changed_;  // offered, completed or over
    std::deque<Task*> offered_;
    std::atomic<std::size_t> on_offer_{0};  // offered_.size(), for readers without the lock
    bool over_ = false;
};

// The used boxes of a partition's two children, accumulated as `partition` does (the
// first of equal values stays, so chunks folded in order give the serial result).
struct UsedBoxes {
    __m128 llo = _mm_set1_ps(std::numeric_limits<float>::infinity());
    __m128 lhi = _mm_set1_ps(-std::numeric_limits<float>::infinity());
    __m128 rlo = llo, rhi = lhi;
    void fold(const UsedBoxes& later) {
        llo = _mm_min_ps(later.llo, llo);
        lhi = _mm_max_ps(later.lhi, lhi);
        rlo = _mm_min_ps(later.rlo, rlo);
        rhi = _mm_max_ps(later.rhi, rhi);
    }
};

// Which children a reference goes to. A reference in the plane goes to both (it has no
// area there to clip); one that straddles it goes to both, clipped.
inline bool goes_left(float lo, float hi, float split) { return lo < split || (lo == split && hi == split); }
inline bool goes_right(float lo, float hi, float split) { return hi > split || (lo == split && hi == split); }

// Chunks of a wide node's references, in order: enough for the lanes to balance.
struct Chunks {
    Chunks(std::size_t items, unsigned lanes)
        : n(items), count(std::max<std::size_t>(1, std::min<std::size_t>(8 * std::size_t{lanes}, items >> 14))) {}
    std::size_t begin(std::size_t c) const { return n * c / count; }
    std::size_t end(std::size_t c) const { return n * (c + 1) / count; }
    std::size_t n, count;
};

class Builder {
public:
    // threads: the lanes a wide node's binning and partition may use (1: never).
    Builder(const TriangleSoup& soup, const KdBuildParams& params, int max_depth, bool parallel, unsigned threads)
        : soup_(soup), p_(params), max_depth_(max_depth), parallel_(parallel), threads_(threads) {}

    // A helper thread: builds offered subtrees until the build is over.
    void help() {
        RefStack rs;
        while (Task* t = tasks_.take()) {
            building_.fetch_add(1, std::memory_order_relaxed);
            run(t, rs);
            building_.fetch_sub(1, std::memory_order_relaxed);
        }
    }
    // Builds a task taken from another thread (or from an outer frame of this one) on `rs`,
    // a stack that nothing else is using meanwhile.
    void run(Task* t, RefStack& rs) {
        try {
            rs.reserve(std::max<std::size_t>(2 * t->n, 16));
            t->out = Output(p_.huge_pages);
            // Room for the subtree's nodes and leaf lists (address space: only what is
            // written becomes resident), so they do not grow by copying.
            t->out.nodes.reserve(t->n / 2 + 16);
            t->out.tri_ids.reserve(2 * t->n + 16);
            t->stack->copy_out(t->first, t->n, rs.data());
            build(rs, 0, t->n, t->cell, t->used, t->depth, t->bad, t->out);
        } catch (...) {
            t->error = std::current_exception();
        }
        tasks_.complete(t);
    }
    void end() { tasks_.end(); }

    // The node whose references are rs.refs[first, first + n).
    // used: the union of the references' boxes (computed by the caller's partition pass,
    // so no node spends an extra pass over its references on it).
    // bad: splits on the path from the root that duplicated most of their references.
    void build(RefStack& rs, std::size_t first, std::size_t n, const Box3f& cell, const Box3f& used, int depth,
               int bad, Output& out);

private:
    struct Side {
        std::size_t first, n;
        Box3f cell, used;
    };
    void emit_leaf(const PrimRef* refs, std::size_t n, const Box3f& cell, int depth, Output& out);
    void count_empty(int depth, Output& out);
    void build_children(RefStack& rs, const Side& left, const Side& right, int depth, int bad, int axis,
                        float split, Output& out);
    bool try_empty_cut(RefStack& rs, std::size_t first, std::size_t n, const Box3f& cell, const Box3f& used,
                       int depth, int bad, Output& out);
    // Returns the children: the right one at [first, first + nr), the left one after it.
    std::pair<Side, Side> partition(RefStack& rs, std::size_t first, std::size_t n, int axis, float split,
                                    const Box3f& lcell, const Box3f& rcell) const;
    // The same children in the same order, the references routed by every lane.
    std::pair<Side, Side> partition_wide(RefStack& rs, std::size_t first, std::size_t n, int axis, float split,
                                         const Box3f& lcell, const Box3f& rcell) const;
    // Routes in[0, n) to the children: the left's to left[nl...], the right's to
    // right[nr...]. `right` may be `in` itself: a reference read gives at most one to the
    // right, so writes never overtake reads.
    void route(const PrimRef* in, std::size_t n, int axis, float split, const Box3f& lcell, const Box3f& rcell,
               PrimRef* left, std::size_t& nl, PrimRef* right, std::size_t& nr, UsedBoxes& used) const;
    // A node near the root, while threads have no subtree of their own to build or to
    // take: its passes over the references are worth splitting between them. (Subtrees on
    // offer count as busy threads: a helper is about to take one, and a wide node beside
    // it would only have the two share cores.)
    bool wide(std::size_t n) const {
        constexpr std::size_t kWideNode = std::size_t{1} << 18;
        return threads_ > 1 && n >= kWideNode &&
               building_.load(std::memory_order_relaxed) + tasks_.on_offer() < threads_;
    }

    const TriangleSoup& soup_;
    const KdBuildParams& p_;
    const int max_depth_;
    const bool parallel_;
    const unsigned threads_;
    std::atomic<unsigned> building_{1};  // threads building a subtree: the caller and busy helpers
    Tasks tasks_;
};

void Builder::count_empty(int depth, Output& out) {
    out.stats.leaves++;
    out.stats.empty_leaves++;
    out.stats.max_depth = std::max(out.stats.max_depth, depth);
}

void Builder::emit_leaf(const PrimRef* refs, std::size_t n, const Box3f& cell, int depth, Output& out) {
    // Reference boxes are conservative (a clipped box can touch a cell the triangle
    // misses): keep exactly the triangles that touch the cell, grown by a few ulps so
    // that nothing a ray could hit inside it is dropped.
    Vec3d lo(cell.lo), hi(cell.hi);
    for (int a = 0; a < 3; ++a) {
        const double m = std::max(std::abs(lo[a]), std::abs(hi[a]));
        const double eps = m * 16.0 * std::numeric_limits<float>::epsilon() + std::numeric_limits<float>::min();
        lo[a] -= eps;
        hi[a] += eps;
    }
    const std::size_t first = out.tri_ids.size();
    auto inside = [&](const Vec3f& v) {
        return lo.x <= v.x && v.x <= hi.x && lo.y <= v.y && v.y <= hi.y && lo.z <= v.z && v.z <= hi.z;
    };
    for (std::size_t i = 0; i < n; ++i) {
        const std::uint32_t id = refs[i].id;
        const Vec3f &a = soup_.v(id, 0), &b = soup_.v(id, 1), &c = soup_.v(id, 2);
        // A corner inside the cell settles it without the separating-axis test.
        if (inside(a) || inside(b) || inside(c) || triangle_overlaps_box(a, b, c, lo, hi)) out.tri_ids.push_back(id);
    }
    const std::size_t kept = out.tri_ids.size() - first;
    out.nodes.push_back(KdNode::leaf(static_cast<std::uint32_t>(first), static_cast<std::uint32_t>(kept)));
    out.stats.leaves++;
    if (kept == 0) out.stats.empty_leaves++;
    out.stats.references += kept;
    out.stats.max_depth = std::max(out.stats.max_depth, depth);
    out.sah_area_sum += static_cast<double>(p_.intersection_cost) * cell.half_area() *
                        static_cast<double>(kept);
}

void Builder::route(const PrimRef* in, std::size_t n, int axis, float split, const Box3f& lcell, const Box3f& rcell,
                    PrimRef* left, std::size_t& nl, PrimRef* right, std::size_t& nr, UsedBoxes& used) const {
    // Boxes in SSE registers (lane 3 unused): Box3f::intersection and extend are
    // std::max / std::min per component, which _mm_max_ps / _mm_min_ps compute exactly
    // with the operands swapped (std::max(a, b) == maxps(b, a), also for -0 and +0).
    const __m128 lcell_lo = load_lo(lcell), lcell_hi = load_hi(lcell), rcell_lo = load_lo(rcell), rcell_hi = load_hi(rcell);
    __m128 lused_lo = used.llo, lused_hi = used.lhi, rused_lo = used.rlo, rused_hi = used.rhi;
    std::size_t l = nl, r = nr;  // in registers: the counts are stored once, at the end
    auto put = [](PrimRef& out, __m128 lo, __m128 hi, std::uint32_t id) {
        _mm_storeu_ps(&out.box.lo.x, lo);  // its lane 3 lands on hi.x, written next
        _mm_storeu_ps(&out.box.hi.x, hi);  // its lane 3 lands on the id, written next
        out.id = id;
    };
    for (std::size_t i = 0; i < n; ++i) {
        // The reference goes straight into registers: a copy on the stack, written as two
        // overlapping 16-byte stores, made each read of it wait for a failed store forward.
        // All of it is read before the writes below, which may reuse its slot.
        const __m128 blo = _mm_loadu_ps(&in[i].box.lo.x), bhi = _mm_loadu_ps(&in[i].box.hi.x);
        const float lo = in[i].box.lo[axis], hi = in[i].box.hi[axis];
        const std::uint32_t id = in[i].id;
        const bool planar = lo == split && hi == split;
        const bool in_left = goes_left(lo, hi, split);
        const bool in_right = goes_right(lo, hi, split);
        if (in_left && in_right && !planar) {
            // Straddles: clip the triangle to each side for tight child boxes.
            const Box3f box = to_box(blo, bhi);
            Box3f halves[2];
            clip_to_half_spaces(soup_.v(id, 0), soup_.v(id, 1), soup_.v(id, 2), axis, split, halves[0], halves[1]);
            for (int side = 0; side < 2; ++side) {
                const Box3f& child = side == 0 ? lcell : rcell;
                const Box3f limit = Box3f::intersection(box, child);
                Box3f clipped = halves[side];
                clipped = clipped.empty() ? limit : Box3f::intersection(widen(clipped), limit);
                if (clipped.empty()) clipped = limit;  // rounding: stay conservative
                const __m128 clo = load_lo(clipped), chi = load_hi(clipped);
                if (side == 0) {
                    lused_lo = _mm_min_ps(clo, lused_lo);
                    lused_hi = _mm_max_ps(chi, lused_hi);
                    put(left[l++], clo, chi, id);
                } else {
                    rused_lo = _mm_min_ps(clo, rused_lo);
                    rused_hi = _mm_max_ps(chi, rused_hi);
                    put(right[r++], clo, chi, id);
                }
            }
        } else {
            if (in_left) {
                const __m128 clo = _mm_max_ps(lcell_lo, blo), chi = _mm_min_ps(lcell_hi, bhi);
                lused_lo = _mm_min_ps(clo, lused_lo);
                lused_hi = _mm_max_ps(chi, lused_hi);
                put(left[l++], clo, chi, id);
            }
            if (in_right) {
                const __m128 clo = _mm_max_ps(rcell_lo, blo), chi = _mm_min_ps(rcell_hi, bhi);
                rused_lo = _mm_min_ps(clo, rused_lo);
                rused_hi = _mm_max_ps(chi, rused_hi);
                put(right[r++], clo, chi, id);
            }
        }
    }
    nl = l;
    nr = r;
    used.llo = lused_lo;
    used.lhi = lused_hi;
    used.rlo = rused_lo;
    used.rhi = rused_hi;
}

std::pair<Builder::Side, Builder::Side> Builder::partition(RefStack& rs, std::size_t first, std::size_t n, int axis,
                                                          float split, const Box3f& lcell, const Box3f& rcell) const {
    const std::size_t top = first + n;
    rs.reserve(top + n);  // the left child holds at most n
    PrimRef* const refs = rs.data();
    PrimRef* const left = refs + top;
    std::size_t nl = 0, nr = 0;
    UsedBoxes used;
    route(refs + first, n, axis, split, lcell, rcell, left, nl, refs + first, nr, used);
    std::memmove(refs + first + nr, left, nl * sizeof(PrimRef));
    return {Side{first + nr, nl, lcell, to_box(used.llo, used.lhi)}, Side{first, nr, rcell, to_box(used.rlo, used.rhi)}};
}

std::pair<Builder::Side, Builder::Side> Builder::partition_wide(RefStack& rs, std::size_t first, std::size_t n,
                                                               int axis, float split, const Box3f& lcell,
                                                               const Box3f& rcell) const {
    // A counting pass places each chunk's left references above the node's range (prefix
    // sums, in chunk order); the chunks are then routed in parallel, each compacting its
    // right references in place at its own start. Moving those down, chunk after chunk,
    // and the left ones behind them leaves the serial partition's result, reference for
    // reference, in the serial partition's memory.
    ThreadPool& pool = ThreadPool::global();
    const Chunks chunks(n, threads_);
    std::vector<std::size_t> at_left(chunks.count + 1, 0), rights(chunks.count, 0);
    {
        const PrimRef* const refs = rs.data() + first;
        pool.parallel_for(chunks.count, [&](std::size_t c, unsigned) {
            std::size_t l = 0;
            for (std::size_t i = chunks.begin(c); i < chunks.end(c); ++i) {
                l += goes_left(refs[i].box.lo[axis], refs[i].box.hi[axis], split) ? 1 : 0;
            }
            at_left[c + 1] = l;
        }, threads_);
    }
    for (std::size_t c = 0; c < chunks.count; ++c) at_left[c + 1] += at_left[c];
    const std::size_t top = first + n, nl = at_left[chunks.count];
    rs.reserve(top + n);  // as the serial partition: the left child holds at most n
    PrimRef* const refs = rs.data();
    std::vector<UsedBoxes> used(chunks.count);
    pool.parallel_for(chunks.count, [&](std::size_t c, unsigned) {
        PrimRef* const mine = refs + first + chunks.begin(c);
        std::size_t l = at_left[c], r = 0;
        route(mine, chunks.end(c) - chunks.begin(c), axis, split, lcell, rcell, refs + top, l, mine, r, used[c]);
        // A chunk routed otherwise than it counted has written over its neighbour's output:
        // fail the build rather than go on with it.
        if (l != at_left[c + 1]) throw std::logic_error("a wide partition miscounted a chunk");
        rights[c] = r;
    }, threads_);
    for (std::size_t c = 1; c < chunks.count; ++c) used[0].fold(used[c]);
    // Each chunk's right references move down onto ground the earlier chunks have left.
    std::size_t nr = 0;
    for (std::size_t c = 0; c < chunks.count; ++c) {
        std::memmove(static_cast<void*>(refs + first + nr), refs + first + chunks.begin(c), rights[c] * sizeof(PrimRef));
        nr += rights[c];
    }
    std::memmove(static_cast<void*>(refs + first + nr), refs + top, nl * sizeof(PrimRef));
    const UsedBoxes& u = used[0];
    return {Side{first + nr, nl, lcell, to_box(u.llo, u.lhi)}, Side{first, nr, rcell, to_box(u.rlo, u.rhi)}};
}

void Builder::build_children(RefStack& rs, const Side& left, const Side& right, int depth, int bad, int axis,
                             float split, Output& out) {
    const std::size_t self = out.nodes.size();
    const std::uint32_t empty_flags = (left.n == 0 ? KdNode::kLeftEmpty : 0u) | (right.n == 0 ? KdNode::kRightEmpty : 0u);
    out.nodes.push_back(KdNode::inner(axis, split, 0, empty_flags));
    out.stats.max_depth = std::max(out.stats.max_depth, depth);
    if (left.n == 0 || right.n == 0) {
        // One child is empty: it costs nothing but a flag; the other follows directly.
        count_empty(depth + 1, out);
        if (left.n == 0) out.nodes[self] = KdNode::inner(axis, split, 1, empty_flags);
        const Side& only = left.n == 0 ? right : left;
        build(rs, only.first, only.n, only.cell, only.used, depth + 1, bad, out);
        return;
    }

    // Big children: the right one is offered to the helpers while this thread builds the left.
    constexpr std::size_t kParallelThreshold = 4096;
    const bool offer = parallel_ && right.n >= kParallelThreshold && left.n >= kParallelThreshold;
    Task task;
    if (offer) {
        task.stack = &rs;
        task.first = right.first;
        task.n = right.n;
        task.cell = right.cell;
        task.used = right.used;
        task.depth = depth + 1;
        task.bad = bad;
    }
    // Whatever happens to the left child, the task must be taken back or finished before
    // this frame (which holds it) goes.
    struct Settle {
        Tasks* tasks;
        Task* task;
        bool settled = false;
        ~Settle() {
            if (!settled && tasks != nullptr && !tasks->reclaim(task)) tasks->wait(task);
        }
    } settle{offer ? &tasks_ : nullptr, &task};
    if (offer) tasks_.offer(&task);
    build(rs, left.first, left.n, left.cell, left.used, depth + 1, bad, out);
    const std::size_t right_offset = out.nodes.size() - self;
    if (right_offset > KdNode::kMaxOffset) throw std::length_error("kd-tree too large for 28-bit child offsets");
    out.nodes[self] = KdNode::inner(axis, split, static_cast<std::uint32_t>(right_offset), 0);
    settle.settled = true;
    if (!offer || tasks_.reclaim(&task)) {
        build(rs, right.first, right.n, right.cell, right.used, depth + 1, bad, out);
        return;
    }
    // The stack for tasks built while waiting: this thread's own is in use down the path.
    std::unique_ptr<RefStack> spare;
    while (Task* other = tasks_.wait_or_take(&task)) {
        if (!spare) spare = std::make_unique<RefStack>();
        run(other, *spare);
    }
    if (task.error) std::rethrow_exception(task.error);
    const Output& right_out = task.out;
    const auto id_base = static_cast<std::uint32_t>(out.tri_ids.size());
    for (KdNode n : right_out.nodes) {
        if (n.is_leaf()) n = KdNode::leaf(n.first() + id_base, n.count());
        out.nodes.push_back(n);
    }
    out.tri_ids.insert(out.tri_ids.end(), right_out.tri_ids.begin(), right_out.tri_ids.end());
    out.stats.leaves += right_out.stats.leaves;
    out.stats.empty_leaves += right_out.stats.empty_leaves;
    out.stats.references += right_out.stats.references;
    out.stats.wide_nodes += right_out.stats.wide_nodes;
    out.stats.max_depth = std::max(out.stats.max_depth, right_out.stats.max_depth);
    out.sah_area_sum += right_out.sah_area_sum;
}

// Paper 000 §4.1: before any other split, cut off an empty slab holding a large share
// of the cell. Tight cells make tight LOD voxels and let rays skip empty space early.
bool Builder::try_empty_cut(RefStack& rs, std::size_t first, std::size_t n, const Box3f& cell,
                            const Box3f& refs_used, int depth, int bad, Output& out) {
    const Box3f used = Box3f::intersection(refs_used, cell);
    if (used.empty()) return false;
    int best_axis = -1, best_side = 0;
    float best_ratio = p_.empty_space_ratio;
    for (int a = 0; a < 3; ++a) {
        const float ext = cell.hi[a] - cell.lo[a];
        if (!(ext > 0)) continue;
        const float lo_gap = (used.lo[a] - cell.lo[a]) / ext;
        const float hi_gap = (cell.hi[a] - used.hi[a]) / ext;
        if (lo_gap >= best_ratio) { best_ratio = lo_gap; best_axis = a; best_side = 0; }
        if (hi_gap >= best_ratio) { best_ratio = hi_gap; best_axis = a; best_side = 1; }
    }
    if (best_axis < 0) return false;
    float split = best_side == 0 ? used.lo[best_axis] : used.hi[best_axis];
    // Quantized: the nearest plane on the empty side of the occupied box, so the cut
    // still leaves every reference on the occupied side.
    std::uint32_t q = 0;
    if (p_.quantized_splits &&
        !format::quantize_split(cell.lo[best_axis], cell.hi[best_axis], split, best_side == 0 ? -1 : 1, q, split)) {
        return false;
    }
    Box3f lcell = cell, rcell = cell;
    lcell.hi[best_axis] = split;
    rcell.lo[best_axis] = split;
    out.sah_area_sum += static_cast<double>(p_.traversal_cost) * cell.half_area();
    // Every reference lies on the occupied side of the cut (touching the plane included).
    const Side occupied_l{first, n, lcell, refs_used}, occupied_r{first, n, rcell, refs_used};
    const Side none_l{first, 0, lcell, Box3f{}}, none_r{first, 0, rcell, Box3f{}};
    if (best_side == 0) {
        build_children(rs, none_l, occupied_r, depth, bad, best_axis, split, out);
    } else {
        build_children(rs, occupied_l, none_r, depth, bad, best_axis, split, out);
    }
    return true;
}

namespace {

constexpr int kStackBins = 64;

// Counts, per axis, the references whose box starts (ends) in each bin. `spare` is room
// for a second set of counters (2 * 3 * bins): neighbouring references mostly fall into
// the same bins, and alternating between two sets halves the chains of increments of
// one counter, each of which waits for the one before.
void bin_references(const PrimRef* refs, std::size_t n, const Binner& binner, std::uint32_t* starts,
                    std::uint32_t* ends, std::uint32_t* spare) {
    // lo's lane 3 is hi.x, hi's is the id: both are ignored.
    auto add = [&](std::size_t i, std::uint32_t* s, std::uint32_t* e) {
        binner.add(_mm_loadu_ps(&refs[i].box.lo.x), _mm_loadu_ps(&refs[i].box.hi.x), s, e);
    };
    constexpr std::size_t kTwoSets = 64;  // below, clearing and summing the second set costs more
    if (n < kTwoSets) {
        for (std::size_t i = 0; i < n; ++i) add(i, starts, ends);
        return;
    }
    const std::size_t per_set = 3 * static_cast<std::size_t>(binner.bins());
    std::fill(spare, spare + 2 * per_set, 0u);
    std::uint32_t *starts2 = spare, *ends2 = spare + per_set;
    std::size_t i = 0;
    for (; i + 1 < n; i += 2) {
        add(i, starts, ends);
        add(i + 1, starts2, ends2);
    }
    if (i < n) add(i, starts, ends);
    for (std::size_t k = 0; k < per_set; ++k) {
        starts[k] += starts2[k];
        ends[k] += ends2[k];
    }
}

// bin_references over chunks on every lane, each into counters of its own, then summed:
// the same counts.
void bin_wide(const PrimRef* refs, std::size_t n, const Binner& binner, unsigned lanes, std::uint32_t* starts,
              std::uint32_t* ends) {
    const std::size_t per_set = 3 * static_cast<std::size_t>(binner.bins());
    ThreadPool& pool = ThreadPool::global();
    // Per lane taking part (parallel_for hands out lanes below `lanes`): starts, ends and
    // bin_references' spare pair.
    std::vector<std::uint32_t> counters(static_cast<std::size_t>(lanes) * 4 * per_set, 0u);
    const Chunks chunks(n, lanes);
    pool.parallel_for(chunks.count, [&](std::size_t c, unsigned lane) {
        std::uint32_t* mine = counters.data() + static_cast<std::size_t>(lane) * 4 * per_set;
        bin_references(refs + chunks.begin(c), chunks.end(c) - chunks.begin(c), binner, mine, mine + per_set,
                       mine + 2 * per_set);
    }, lanes);
    for (unsigned lane = 0; lane < lanes; ++lane) {
        const std::uint32_t* mine = counters.data() + static_cast<std::size_t>(lane) * 4 * per_set;
        for (std::size_t k = 0; k < per_set; ++k) {
            starts[k] += mine[k];
            ends[k] += mine[per_set + k];
        }
    }
}

// SAH costs of the candidate planes 1 ... bins - 1 of one axis, four at a time: the
// child areas in float and the cost in double, each operation the one the scalar
//   Ct + ci * (double(wl * perimeter + cap) * nl + double(wr * perimeter + cap) * nr)
// with wl = step * i, wr = ext - wl does, so the costs are bit for bit the same.
void sah_costs(int bins, float step, float ext, float perimeter, float cap, float traversal_cost, double ci_per_area,
               const std::uint32_t* counts_left, const std::uint32_t* counts_right, double* costs) {
    const __m128 step4 = _mm_set1_ps(step), ext4 = _mm_set1_ps(ext), per4 = _mm_set1_ps(perimeter), cap4 = _mm_set1_ps(cap);
    const __m128d ct = _mm_set1_pd(static_cast<double>(traversal_cost)), ci = _mm_set1_pd(ci_per_area);
    for (int i = 1; i < bins; i += 4) {
        const __m128 wl = _mm_mul_ps(step4, _mm_cvtepi32_ps(_mm_setr_epi32(i, i + 1, i + 2, i + 3)));
        const __m128 wr = _mm_sub_ps(ext4, wl);
        const __m128 al = _mm_add_ps(_mm_mul_ps(wl, per4), cap4), ar = _mm_add_ps(_mm_mul_ps(wr, per4), cap4);
        // Counts stay below 2^31 (a part has fewer triangles), so the signed conversion holds.
        const __m128i nl = _mm_loadu_si128(reinterpret_cast<const __m128i*>(counts_left + i));
        const __m128i nr = _mm_loadu_si128(reinterpret_cast<const __m128i*>(counts_right + i));
        for (int half = 0; half < 2; ++half) {
            const __m128 al2 = half == 0 ? al : _mm_movehl_ps(al, al), ar2 = half == 0 ? ar : _mm_movehl_ps(ar, ar);
            const __m128i nl2 = half == 0 ? nl : _mm_shuffle_epi32(nl, 0xEE), nr2 = half == 0 ? nr : _mm_shuffle_epi32(nr, 0xEE);
            const __m128d sum = _mm_add_pd(_mm_mul_pd(_mm_cvtps_pd(al2), _mm_cvtepi32_pd(nl2)),
                                           _mm_mul_pd(_mm_cvtps_pd(ar2), _mm_cvtepi32_pd(nr2)));
            _mm_storeu_pd(costs + i + 2 * half, _mm_add_pd(ct, _mm_mul_pd(ci, sum)));
        }
    }
}

}  // namespace

void Builder::build(RefStack& rs, std::size_t first, std::size_t n, const Box3f& cell, const Box3f& used, int depth,
                    int bad, Output& out) {
    if (n == 0 || depth >= max_depth_) {
        emit_leaf(rs.data() + first, n, cell, depth, out);
        return;
    }
    if (try_empty_cut(rs, first, n, cell, used, depth, bad, out)) return;
    if (n <= static_cast<std::size_t>(p_.leaf_size)) {
        emit_leaf(rs.data() + first, n, cell, depth, out);
        return;
    }
    const PrimRef* refs = rs.data() + first;

    // Binned SAH over the three axes, binned in one pass over the references. Small
    // nodes get fewer bins: past ~n candidates per axis the sweep costs more than the
    // binning and finds nothing better.
    const int bins = std::max(4, std::min(p_.bins, static_cast<int>(std::min<std::size_t>(n, 1u << 20)) + 4));
    const auto nb = static_cast<std::size_t>(bins);
    const double area = cell.half_area();
    const double ci_per_area = area > 0 ? p_.intersection_cost / area : 0.0;
    double best_cost = static_cast<double>(p_.intersection_cost) * static_cast<double>(n);
    int best_axis = -1;
    float best_split = 0;
    std::size_t best_left = 0, best_right = 0;
    std::uint32_t stack_bins[2 * 2 * 3 * kStackBins];  // starts, ends; the binning's spare set
    std::vector<std::uint32_t> heap_bins;
    std::uint32_t* starts = stack_bins;
    if (bins > kStackBins) {
        heap_bins.resize(2 * 2 * 3 * nb);
        starts = heap_bins.data();
    }
    std::uint32_t* ends = starts + 3 * nb;
    std::fill(starts, starts + 2 * 3 * nb, 0u);
    // Padded: sah_costs works four candidates at a time.
    alignas(16) double stack_costs[kStackBins + 4];
    alignas(16) std::uint32_t stack_counts[2 * (kStackBins + 4)];
    std::vector<double> heap_costs;
    std::vector<std::uint32_t> heap_counts;
    double* costs = stack_costs;
    std::uint32_t* counts_left = stack_counts;
    if (bins > kStackBins) {
        heap_costs.resize(nb + 4);
        heap_counts.resize(2 * (nb + 4));
        costs = heap_costs.data();
        counts_left = heap_counts.data();
    }
    std::uint32_t* counts_right = counts_left + nb + 4;
    std::fill(counts_left, counts_left + 2 * (nb + 4), 0u);
    const bool wide_node = wide(n);
    if (wide_node) {
        out.stats.wide_nodes++;
        bin_wide(refs, n, Binner(cell, bins), threads_, starts, ends);
    } else {
        bin_references(refs, n, Binner(cell, bins), starts, ends, starts + 2 * 3 * nb);
    }
    for (int a = 0; a < 3; ++a) {
        const float lo = cell.lo[a], ext = cell.hi[a] - cell.lo[a];
        if (!(ext > 0) || area <= 0) continue;
        const std::uint32_t* st = starts + static_cast<std::size_t>(a) * nb;
        const std::uint32_t* en = ends + static_cast<std::size_t>(a) * nb;
        const Vec3f e = cell.extent();
        const float o1 = e[(a + 1) % 3], o2 = e[(a + 2) % 3];
        // Child half-areas are linear in the split position: w * perimeter + cap. The
        // counts come first (a prefix sum), so the cost loop has no dependency between
        // candidates and vectorises; the scan then keeps the first lowest, as one loop would.
        const float perimeter = o1 + o2, cap = o1 * o2, step = ext / static_cast<float>(bins);
        std::uint32_t n_left = 0, n_right = static_cast<std::uint32_t>(n);
        for (int i = 1; i < bins; ++i) {
            n_left += st[i - 1];
            n_right -= en[i - 1];
            counts_left[i] = n_left;
            counts_right[i] = n_right;
        }
        sah_costs(bins, step, ext, perimeter, cap, p_.traversal_cost, ci_per_area, counts_left, counts_right, costs);
        for (int i = 1; i < bins; ++i) {
            if (costs[i] < best_cost) {
                best_cost = costs[i];
                best_axis = a;
                best_split = lo + step * static_cast<float>(i);
                best_left = counts_left[i];
                best_right = counts_right[i];
            }
        }
    }
    if (best_axis < 0) {
        if (n <= static_cast<std::size_t>(p_.median_fallback)) {
            emit_leaf(refs, n, cell, depth, out);
            return;
        }
        // SAH sees no gain but the leaf would be huge: split the longest axis in the middle.
        const Vec3f e = cell.extent();
        best_axis = e.x >= e.y && e.x >= e.z ? 0 : (e.y >= e.z ? 1 : 2);
        best_split = 0.5f * (cell.lo[best_axis] + cell.hi[best_axis]);
        best_left = best_right = 0;
        for (std::size_t i = 0; i < n; ++i) {
            const float lo = refs[i].box.lo[best_axis], hi = refs[i].box.hi[best_axis];
            best_left += goes_left(lo, hi, best_split) ? 1 : 0;
            best_right += goes_right(lo, hi, best_split) ? 1 : 0;
        }
    }

    if (p_.quantized_splits) {
        std::uint32_t q = 0;
        if (!format::quantize_split(cell.lo[best_axis], cell.hi[best_axis], best_split, 0, q, best_split)) {
            emit_leaf(refs, n, cell, depth, out);  // too narrow a cell for the grid
            return;
        }
    }

    // The SAH cannot see duplication: where triangles meet at a vertex (fans) or run
    // through many cells, a split can copy most references to both sides and still
    // score a gain on flat cells. A path may take a few such splits, then the node
    // becomes a leaf instead of doubling its references level after level.
    constexpr int kMaxBadSplits = 3;
    const bool duplicating = 2 * (best_left + best_right) > 3 * n;
    if (duplicating && bad >= kMaxBadSplits) {
        emit_leaf(refs, n, cell, depth, out);
        return;
    }
    Box3f lcell = cell, rcell = cell;
    lcell.hi[best_axis] = best_split;
    rcell.lo[best_axis] = best_split;
    const auto [left, right] = wide_node ? partition_wide(rs, first, n, best_axis, best_split, lcell, rcell)
                                         : partition(rs, first, n, best_axis, best_split, lcell, rcell);
    out.sah_area_sum += static_cast<double>(p_.traversal_cost) * area;
    build_children(rs, left, right, depth, bad + (duplicating ? 1 : 0), best_axis, best_split, out);
}

}  // namespace

KdTree build_kdtree(const TriangleSoup& soup, const KdBuildParams& params, const Box3f* cell) {
    const auto start = std::chrono::steady_clock::now();
    KdTree tree;
    if (soup.count >= KdNode::kMaxCount) throw std::length_error("too many triangles for an in-core kd-tree");

    // Reference creation is embarrassingly parallel; the pool is shared with rendering.
    // Room for the path's references: measured peaks are 2.3x the triangles.
    RefStack rs;
    rs.reserve(std::max<std::size_t>(3 * soup.count, 16));
    PrimRef* const refs = rs.data();
    ThreadPool& pool = ThreadPool::global();
    const std::size_t chunk = 1 << 16;
    const std::size_t chunks = (soup.count + chunk - 1) / chunk;
    std::vector<Box3f> chunk_bounds(chunks);
    std::vector<std::size_t> chunk_dropped(chunks, 0), chunk_kept(chunks, 0);
    // Zero-area triangles (collinear in the stored float coordinates) are left out (has_area).
    constexpr std::uint32_t kDropped = 0xffffffffu, kOutside = 0xfffffffeu;
    pool.parallel_for(chunks, [&](std::size_t c, unsigned) {
        Box3f bounds;
        std::size_t dropped = 0, kept = 0;
        const std::size_t end = std::min(soup.count, (c + 1) * chunk);
        for (std::size_t i = c * chunk; i < end; ++i) {
            if (!has_area(soup.v(i, 0), soup.v(i, 1), soup.v(i, 2))) {
                refs[i] = {Box3f{}, kDropped};
                ++dropped;
                continue;
            }
            Box3f box;
            for (int k = 0; k < 3; ++k) box.extend(soup.v(i, k));
            const bool inside = cell == nullptr || (cell->lo.x <= box.lo.x && cell->lo.y <= box.lo.y &&
                                                    cell->lo.z <= box.lo.z && box.hi.x <= cell->hi.x &&
                                                    box.hi.y <= cell->hi.y && box.hi.z <= cell->hi.z);
            // Only a triangle the cell cuts gets a clipped (and conservatively widened)
            // box. Widening every box would make all triangles sharing a vertex on a
            // split plane straddle it: at the centre of a fan, every one of them.
            if (!inside) {
                const Box3f clipped = clip_to_box(soup.v(i, 0), soup.v(i, 1), soup.v(i, 2), *cell);
                // Touching the cell only in rounding still keeps the triangle (never drop
                // a triangle from a cell it may overlap); one clearly outside is left out.
                box = Box3f::intersection(widen(clipped.empty() ? box : clipped), *cell);
                if (box.empty()) {
                    refs[i] = {Box3f{}, kOutside};
                    continue;
                }
            }
            refs[i] = {box, static_cast<std::uint32_t>(i)};
            bounds.extend(box);
            ++kept;
        }
        chunk_bounds[c] = bounds;
        chunk_dropped[c] = dropped;
        chunk_kept[c] = kept;
    }, params.threads);
    std::size_t degenerate = 0, root_refs = 0;
    for (std::size_t c = 0; c < chunks; ++c) {
        degenerate += chunk_dropped[c];
        root_refs += chunk_kept[c];
    }
    // A serial pass over every reference, so only where there are any to remove.
    if (root_refs < soup.count) {
        std::remove_if(refs, refs + soup.count, [](const PrimRef& r) { return r.id >= kOutside; });
    }
    Box3f used;
    for (const Box3f& b : chunk_bounds) used.extend(b);
    tree.bounds = cell != nullptr ? *cell : used;
    if (tree.bounds.empty()) tree.bounds = Box3f{{0, 0, 0}, {0, 0, 0}};

    int max_depth = params.max_depth;
    if (max_depth <= 0) {
        max_depth = static_cast<int>(8 + 1.3 * std::log2(static_cast<double>(std::max<std::size_t>(soup.count, 1))));
        max_depth = std::min(max_depth, 60);
    }
    const unsigned threads = params.threads == 0 ? hardware_threads() : params.threads;
    const unsigned helpers = root_refs >= (1u << 14) ? threads - 1 : 0;  // small trees: one thread
    Builder builder(soup, params, max_depth, helpers > 0, helpers > 0 ? std::min(threads, ThreadPool::global().lanes()) : 1);
    Output out(params.huge_pages);
    // Measured: about one node and three leaf references per triangle.
    out.nodes.reserve(soup.count + soup.count / 4 + 16);
    out.tri_ids.reserve(3 * soup.count + 16);
    {
        std::vector<std::thread> help;
        struct Join {
            Builder& builder;
            std::vector<std::thread>& threads;
            ~Join() {
                builder.end();
                for (auto& t : threads) t.join();
            }
        } join{builder, help};
        for (unsigned i = 0; i < helpers; ++i) help.emplace_back([&builder] { builder.help(); });
        builder.build(rs, 0, root_refs, tree.bounds, used, 0, 0, out);
    }

    tree.nodes = std::move(out.nodes);
    tree.tri_ids = std::move(out.tri_ids);
    tree.stats = out.stats;
    tree.stats.nodes = tree.nodes.size();
    tree.stats.degenerate = degenerate;
    const double root_area = tree.bounds.half_area();
    tree.stats.sah_cost = root_area > 0 ? out.sah_area_sum / root_area : 0;
    tree.stats.build_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    return tree;
}

}  // namespace vastray
