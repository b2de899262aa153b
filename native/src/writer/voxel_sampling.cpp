#include "writer/voxel_sampling.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "vastray/format.h"

namespace vastray::writer {

Proxy leaf_proxy(const Vec3f* corners, const std::uint32_t* colours, const std::uint32_t* tris,
                 std::uint32_t count, const Box3f& cell) {
    Proxy q;
    Vec3f csum[6], nsum[6];
    float wsum[6] = {}, area_sum = 0;
    Vec3f cflat, nflat, first_normal;
    for (std::uint32_t i = 0; i < count; ++i) {
        const Vec3f* v = corners + 3 * static_cast<std::size_t>(tris[i]);
        for (int k = 0; k < 3; ++k) q.box.extend(v[k]);
        Vec3f n = cross(v[1] - v[0], v[2] - v[0]);
        const float area = 0.5f * length(n);
        if (!(area > 0)) continue;
        n = n / (2.0f * area);
        Vec3f c(0.75f, 0.75f, 0.75f);
        if (colours != nullptr) {
            const std::uint32_t rgb = colours[tris[i]];
            c = Vec3f(static_cast<float>(rgb & 255u), static_cast<float>((rgb >> 8) & 255u),
                      static_cast<float>((rgb >> 16) & 255u)) / 255.0f;
        }
        cflat += c * area;
        area_sum += area;
        // Unoriented mean normal (signs aligned to the first triangle), for faces that
        // see the leaf edge-on.
        if (dot(first_normal, first_normal) == 0) first_normal = n;
        nflat += n * (dot(n, first_normal) < 0 ? -area : area);
        for (int f = 0; f < 6; ++f) {
            // Weighted by the area seen from face f, oriented towards that viewer.
            const float proj = dot(n, outward(f));
            const float w = area * std::abs(proj);
            csum[f] += c * w;
            nsum[f] += n * (proj < 0 ? -w : w);
            wsum[f] += w;
        }
    }
    q.box = Box3f::intersection(q.box, cell);
    if (q.box.empty()) q.box = cell;
    const Vec3f grey(0.75f, 0.75f, 0.75f);
    for (int f = 0; f < 6; ++f) {
        if (wsum[f] > 0 && dot(nsum[f], nsum[f]) > 0) {
            q.s.colour[f] = csum[f] / wsum[f];
            q.s.normal[f] = normalize(nsum[f]);
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
    const Proxy* hit[64];
    float depth[64];
    for (int f = 0; f < 6; ++f) {
        const int axis = f / 2, side = f % 2, u = (axis + 1) % 3, v = (axis + 2) % 3;
        const float du = (cell.hi[u] - cell.lo[u]) / static_cast<float>(k);
        const float dv = (cell.hi[v] - cell.lo[v]) / static_cast<float>(k);
        std::fill(hit, hit + k * k, nullptr);
        std::fill(depth, depth + k * k, std::numeric_limits<float>::infinity());
        // Ray (i, j) passes through (lo + (i + 0.5) du, lo + (j + 0.5) dv): each proxy
        // covers a rectangle of rays, found by arithmetic instead of testing each ray.
        auto range = [k](float lo, float hi, float origin, float step, int& first, int& last) {
            if (!(step > 0)) {
                first = 0;
                last = lo <= origin && origin <= hi ? k - 1 : -1;
                return;
            }
            first = std::max(0, static_cast<int>(std::ceil((lo - origin) / step - 0.5f)));
            last = std::min(k - 1, static_cast<int>(std::floor((hi - origin) / step - 0.5f)));
        };
        for (const std::vector<Proxy>* t : {a, b}) {
            if (t == nullptr) continue;
            for (const Proxy& q : *t) {
                int i0, i1, j0, j1;
                range(q.box.lo[u], q.box.hi[u], cell.lo[u], du, i0, i1);
                range(q.box.lo[v], q.box.hi[v], cell.lo[v], dv, j0, j1);
                const float d = side == 0 ? q.box.lo[axis] : -q.box.hi[axis];
                for (int i = i0; i <= i1; ++i) {
                    for (int j = j0; j <= j1; ++j) {
                        if (d < depth[i * k + j]) {
                            depth[i * k + j] = d;
                            hit[i * k + j] = &q;
                        }
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

QuantisedVoxel quantise_voxel(const FaceSamples& s, float colour_tolerance, float normal_tolerance) {
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
        q.samples[0] = format::pack_sample(cm, nm, true);
        q.count = 1;
        for (int f = 0; f < 6; ++f) {
            q.seen.colour[f] = cm;
            q.seen.normal[f] = nm * (dot(nm, outward(f)) < 0 ? -1.0f : 1.0f);
        }
    } else {
        for (int f = 0; f < 6; ++f) q.samples[f] = format::pack_sample(s.colour[f], s.normal[f], false);
        q.count = 6;
    }
    return q;
}

}  // namespace vastray::writer
