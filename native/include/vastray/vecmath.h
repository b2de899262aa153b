// Small fixed-size vector types. Geometry is float (stored relative to the model
// centre); camera and world-space math is double so far-away models keep detail.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

namespace vastray {

template <typename T>
struct Vec3 {
    T x = 0, y = 0, z = 0;

    constexpr Vec3() = default;
    constexpr Vec3(T x_, T y_, T z_) : x(x_), y(y_), z(z_) {}
    template <typename U>
    constexpr explicit Vec3(const Vec3<U>& o)
        : x(static_cast<T>(o.x)), y(static_cast<T>(o.y)), z(static_cast<T>(o.z)) {}

    // Index through a pointer to the (standard-layout, contiguous) members: the
    // conditional form compiles to branches in the hot loops.
    T operator[](int i) const { return (&x)[i]; }
    T& operator[](int i) { return (&x)[i]; }

    Vec3 operator+(const Vec3& o) const { return {x + o.x, y + o.y, z + o.z}; }
    Vec3 operator-(const Vec3& o) const { return {x - o.x, y - o.y, z - o.z}; }
    Vec3 operator-() const { return {-x, -y, -z}; }
    Vec3 operator*(T s) const { return {x * s, y * s, z * s}; }
    Vec3 operator/(T s) const { return {x / s, y / s, z / s}; }
    Vec3 operator*(const Vec3& o) const { return {x * o.x, y * o.y, z * o.z}; }
    Vec3& operator+=(const Vec3& o) { x += o.x; y += o.y; z += o.z; return *this; }
};

static_assert(sizeof(Vec3<float>) == 3 * sizeof(float), "Vec3 members must be contiguous");
using Vec3f = Vec3<float>;
using Vec3d = Vec3<double>;

template <typename T>
inline T dot(const Vec3<T>& a, const Vec3<T>& b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
template <typename T>
inline Vec3<T> cross(const Vec3<T>& a, const Vec3<T>& b) {
    return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

// Whether a triangle covers any surface: its normal, in double arithmetic on the float
// corners, is not zero. The others are left out everywhere: by the kd-tree, the wide BVH,
// the in-core scene's bounds (the kd-tree's root cell) and the out-of-core builder's
// records. The sheared 2D test could otherwise give a zero-area triangle a sliver of area.
inline bool has_area(const Vec3<float>& a, const Vec3<float>& b, const Vec3<float>& c) {
    const Vec3<double> n = cross(Vec3<double>(b) - Vec3<double>(a), Vec3<double>(c) - Vec3<double>(a));
    return n.x != 0 || n.y != 0 || n.z != 0;
}

template <typename T>
inline T length(const Vec3<T>& a) { return std::sqrt(dot(a, a)); }
template <typename T>
inline Vec3<T> normalize(const Vec3<T>& a) { return a / length(a); }
template <typename T>
inline Vec3<T> vmin(const Vec3<T>& a, const Vec3<T>& b) {
    return {std::min(a.x, b.x), std::min(a.y, b.y), std::min(a.z, b.z)};
}
template <typename T>
inline Vec3<T> vmax(const Vec3<T>& a, const Vec3<T>& b) {
    return {std::max(a.x, b.x), std::max(a.y, b.y), std::max(a.z, b.z)};
}
template <typename T>
inline bool all_finite(const Vec3<T>& a) {
    return std::isfinite(a.x) && std::isfinite(a.y) && std::isfinite(a.z);
}

struct Box3f {
    Vec3f lo{std::numeric_limits<float>::infinity(), std::numeric_limits<float>::infinity(),
             std::numeric_limits<float>::infinity()};
    Vec3f hi{-std::numeric_limits<float>::infinity(), -std::numeric_limits<float>::infinity(),
             -std::numeric_limits<float>::infinity()};

    bool empty() const { return lo.x > hi.x || lo.y > hi.y || lo.z > hi.z; }
    void extend(const Vec3f& p) { lo = vmin(lo, p); hi = vmax(hi, p); }
    void extend(const Box3f& b) { lo = vmin(lo, b.lo); hi = vmax(hi, b.hi); }
    Vec3f extent() const { return hi - lo; }
    float half_area() const {
        const Vec3f e = extent();
        return e.x * e.y + e.y * e.z + e.z * e.x;
    }
    static Box3f intersection(const Box3f& a, const Box3f& b) {
        Box3f r;
        r.lo = vmax(a.lo, b.lo);
        r.hi = vmin(a.hi, b.hi);
        return r;
    }
};

}  // namespace vastray
