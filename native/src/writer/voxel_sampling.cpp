#include "writer/voxel_sampling.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "vastray/format.h"
#include "writer/triangle_blocks.h"

namespace vastray::writer {

Facet facet_of(const Vec3f* v) {
    Facet f;
    const Vec3f n = cross(v[1] - v[0], v[2] - v[0]);
    f.area = 0.5f * length(n);
    if (f.area > 0) f.normal = n / (2.0f * f.area);
    return f;
}

Proxy leaf_proxy(const TriangleSource& src, const std::uint32_t* tris, std::uint32_t count, const Box3f& cell) {
    Proxy q;
    // Per axis: the two faces see the same projected area, so they share the colour
    // and weight sums, and their normal sums are exact negatives of each other.
    Vec3f csum[3], nsum[3];
    float wsum[3] = {}, area_sum = 0;
    Vec3f cflat, nflat, first_normal;
    for (std::uint32_t i = 0; i < count; ++i) {
        const Vec3f* v = src.corners(tris[i]);
        for (int k = 0; k < 3; ++k) q.box.extend(v[k]);
        const Facet& t = src.facets[tris[i]];
        const float area = t.area;
        if (!(area > 0)) continue;
        const Vec3f n = t.normal;
        Vec3f c(0.75f, 0.75f, 0.75f);
        if (src.has_colours) {
            const std::uint32_t rgb = src.colour(tris[i]);
            c = Vec3f(static_cast<float>(rgb & 255u), static_cast<float>((rgb >> 8) & 255u),
                      static_cast<float>((rgb >> 16) & 255u)) / 255.0f;
        }
        cflat += c * area;
        area_sum += area;
        // Unoriented mean normal (signs aligned to the first triangle), for faces that
        // see the leaf edge-on.
        if (dot(first_normal, first_normal) == 0) first_normal = n;
        nflat += n * (dot(n, first_normal) < 0 ? -area : area);
        for (int a = 0; a < 3; ++a) {
            // Weighted by the area seen from the face, oriented towards the viewer on
            // the + side (the - side's viewer sees the opposite orientation).
            const float proj = n[a];
            const float w = area * std::abs(proj);
            csum[a] += c * w;
            nsum[a] += n * (proj < 0 ? -w : w);
            wsum[a] += w;
        }
    }
    q.box = Box3f::intersection(q.box, cell);
    if (q.box.empty()) q.box = cell;
    const Vec3f grey(0.75f, 0.75f, 0.75f);
    for (int f = 0; f < 6; ++f) {
        const int a = f / 2;
        if (wsum[a] > 0 && dot(nsum[a], nsum[a]) > 0) {
            q.s.colour[f] = csum[a] / wsum[a];
            q.s.normal[f] = normalize(f % 2 != 0 ? nsum[a] : -nsum[a]);
        } else {
            // Edge-on (every triangle parallel to the view): the surface normal still
            // says how the leaf shades from nearby directions.
            q.s.colour[f] = area_sum > 0 ? cflat / area_sum : grey;
            const Vec3f o = outward(f);
            const float side = dot(nflat, o) < 0 ? -1.0f : 1.0f;
            q.s.normal[f] = dot(nflat, nflat) > 0 ? normalize(nflat) * side : o;
        }
    }
    return q;
}

FaceSamples sample_voxel(const Box3f& cell, const std::vector<Proxy>* a, const std::vector<Proxy>* b, int rays) {
    FaceSamples out;
    bool have[6] = {};
    const int k = std::clamp(rays, 1, 8);
    // Ray (i, j) of a face passes through (lo + (i + 0.5) du, lo + (j + 0.5) dv) on the
    // face's two other axes: each proxy covers a rectangle of rays, found by arithmetic
    // instead of testing each ray. The rows a proxy covers along an axis do not depend
    // on the face, so they are found once per proxy and axis.
    struct Span {
        const Proxy* q;
        int first[3], last[3];
    };
    Span spans[64];
    std::vector<Span> more;
    Span* span = spans;
    std::size_t count = 0;
    for (const std::vector<Proxy>* t : {a, b}) count += t == nullptr ? 0 : t->size();
    if (count > 64) {
        more.resize(count);
        span = more.data();
    }
    float step[3];
    for (int c = 0; c < 3; ++c) step[c] = (cell.hi[c] - cell.lo[c]) / static_cast<float>(k);
    std::size_t m = 0;
    for (const std::vector<Proxy>* t : {a, b}) {
        if (t == nullptr) continue;
        for (const Proxy& q : *t) {
            Span& sp = span[m++];
            sp.q = &q;
            for (int c = 0; c < 3; ++c) {
                const float lo = q.box.lo[c], hi = q.box.hi[c], origin = cell.lo[c], d = step[c];
                if (!(d > 0)) {
                    sp.first[c] = 0;
                    sp.last[c] = lo <= origin && origin <= hi ? k - 1 : -1;
                    continue;
                }
                sp.first[c] = std::max(0, static_cast<int>(std::ceil((lo - origin) / d - 0.5f)));
                sp.last[c] = std::min(k - 1, static_cast<int>(std::floor((hi - origin) / d - 0.5f)));
            }
        }
    }
    const Proxy* hit[64];
    float depth[64];
    for (int f = 0; f < 6; ++f) {
        const int axis = f / 2, side = f % 2, u = (axis + 1) % 3, v = (axis + 2) % 3;
        std::fill(hit, hit + k * k, nullptr);
        std::fill(depth, depth + k * k, std::numeric_limits<float>::infinity());
        for (std::size_t p = 0; p < m; ++p) {
            const Span& sp = span[p];
            const float d = side == 0 ? sp.q->box.lo[axis] : -sp.q->box.hi[axis];
            for (int i = sp.first[u]; i <= sp.last[u]; ++i) {
                for (int j = sp.first[v]; j <= sp.last[v]; ++j) {
                    if (d < depth[i * k + j]) {
                        depth[i * k + j] = d;
                        hit[i * k + j] = sp.q;
                    }
                }
            }
        }
    Vec3f colour, normal;
        int hits = 0;
        for (int r = 0; r < k * k; ++r) {
            if (hit[r] == nullptr) continue;
            colour += hit[r]->s.colour[f];
            normal += hit[r]->s.normal[f];
            ++hits;
        }
        if (hits > 0 && dot(normal, normal) > 0) {
            out.colour[f] = colour / static_cast<float>(hits);
            out.normal[f] = normalize(normal);
            have[f] = true;
        }
    }
    // Faces no ray saw anything through (thin geometry between the rays) borrow from
    // the faces that did, or from every proxy when none did.
    Vec3f colour_sum, normal_sum;
    int seen = 0;
    for (int f = 0; f < 6; ++f) {
        if (!have[f]) continue;
        colour_sum += out.colour[f];
        ++seen;
    }
    if (seen == 0) {
        int n = 0;
        for (const std::vector<Proxy>* t : {a, b}) {
            if (t == nullptr) continue;
            for (const Proxy& q : *t) {
                for (int f = 0; f < 6; ++f) colour_sum += q.s.colour[f];
                n += 6;
            }
        }
        colour_sum = n > 0 ? colour_sum / static_cast<float>(n) : Vec3f(0.75f, 0.75f, 0.75f);
    } else {
        colour_sum = colour_sum / static_cast<float>(seen);
    }
    for (int f = 0; f < 6; ++f) {
        if (have[f]) continue;
        const Vec3f o = outward(f);
        normal_sum = Vec3f();
        for (int g = 0; g < 6; ++g) {
            if (have[g]) normal_sum += out.normal[g] * (dot(out.normal[g], o) < 0 ? -1.0f : 1.0f);
        }
        out.colour[f] = colour_sum;
        out.normal[f] = dot(normal_sum, normal_sum) > 0 ? normalize(normal_sum) : o;
    }
    return out;
}

QuantisedVoxel quantise_voxel(const FaceSamples& s, float colour_tolerance, float normal_tolerance, bool packed) {
    Vec3f cm, nm;
    for (int f = 0; f < 6; ++f) {
        cm += s.colour[f];
        nm += s.normal[f] * (dot(s.normal[f], s.normal[0]) < 0 ? -1.0f : 1.0f);
    }
    cm = cm / 6.0f;
    nm = dot(nm, nm) > 0 ? normalize(nm) : s.normal[0];
    bool one = true;
    for (int f = 0; f < 6 && one; ++f) {
        const Vec3f n = s.normal[f] * (dot(s.normal[f], nm) < 0 ? -1.0f : 1.0f);
        for (int c = 0; c < 3; ++c) {
            if (std::abs(s.colour[f][c] - cm[c]) > colour_tolerance || std::abs(n[c] - nm[c]) > normal_tolerance) {
                one = false;
            }
        }
    }
    QuantisedVoxel q;
    q.seen = s;
    if (one) {
        q.words[0] = format::pack_sample(cm, nm, true);
        q.count = 1;
        for (int f = 0; f < 6; ++f) {
            q.seen.colour[f] = cm;
            q.seen.normal[f] = nm * (dot(nm, outward(f)) < 0 ? -1.0f : 1.0f);
        }
    } else {
        std::uint32_t six[6], four[4];
        for (int f = 0; f < 6; ++f) six[f] = format::pack_sample(s.colour[f], s.normal[f], false);
        if (packed && format::pack_voxel(six, four)) {
            std::copy(four, four + 4, q.words);
            q.count = 4;
        } else {
            std::copy(six, six + 6, q.words);
            q.count = 6;
        }
    }
    return q;
}

}  // namespace vastray::writer
