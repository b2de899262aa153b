// The edge-aware filter of the indirect mode: a cross-bilateral filter of the noisy
// indirect light, guided by each pixel's depth and normal (paper 000 filters its
// diffuse rays' light with a bilateral filter, [TM98]). It runs as an a-trous wavelet
// (Dammertz et al. 2010): three rounds of a 5-tap B3 spline kernel with holes (steps 1,
// 2, 4), each round a horizontal then a vertical pass, so a 2-sample image is averaged
// over about 20 pixels each way at the cost of 30 taps per pixel.
//
// The weights come from the guides only, never from the noisy values: the filter is
// linear in the light, so averaging the filtered passes of a still view is the same as
// filtering their average (what lets the server refine by averaging frames).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <vector>

#include "vastray/isa.h"
#include "vastray/thread_pool.h"

VASTRAY_KERNEL_BEGIN
namespace denoise {

struct Guides {
    int width = 0, height = 0;
    const float* depth = nullptr;   // per pixel, inf where nothing was hit (left alone)
    const float* normal = nullptr;  // 3 per pixel: the unit normal the shading used
    float pixel_angle = 0;          // width of a pixel at unit distance
    float pixel_size = 0;           // orthographic views: a pixel's width, the same at every depth
};

namespace detail {

// Edge-stopping weight of pixel q for pixel p at `offset` pixels: normals within a few
// degrees and depths on the same surface.
inline float edge_weight(const Guides& g, std::size_t p, std::size_t q, int offset) {
    const float zq = g.depth[q];
    if (!(zq < std::numeric_limits<float>::infinity())) return 0.0f;
    const float* np = g.normal + 3 * p;
    const float* nq = g.normal + 3 * q;
    float c = std::max(0.0f, np[0] * nq[0] + np[1] * nq[1] + np[2] * nq[2]);
    c *= c;
    c *= c;
    c *= c;
    c *= c;  // cos^16: about 17 degrees halves the weight
    const float zp = g.depth[p];
    // Depth tolerance: what a surface seen at 60 degrees from its normal spans over the
    // offset, plus 1 % for curvature.
    // (Orthographic: a pixel's width is the same at every depth, and the 1 % is of the
    // view's height, which the depth of a perspective view stands for.)
    const float tol = g.pixel_size > 0
                          ? g.pixel_size * (2.0f * static_cast<float>(offset) + 0.01f * static_cast<float>(g.height))
                          : zp * (2.0f * g.pixel_angle * static_cast<float>(offset) + 0.01f);
    const float dz = (zp - zq) / tol;
    return c / (1.0f + dz * dz);
}

// Each row's run of pixels from its first to its last one that hit something (first >
// last: none), which is all a pass has to filter.
struct Span {
    int first, last;
};

inline std::vector<Span> hit_spans(const Guides& g) {
    std::vector<Span> spans(static_cast<std::size_t>(g.height));
    for (int y = 0; y < g.height; ++y) {
        const float* row = g.depth + static_cast<std::size_t>(y) * g.width;
        int first = 0, last = g.width - 1;
        while (first < g.width && !(row[first] < std::numeric_limits<float>::infinity())) ++first;
        while (last >= first && !(row[last] < std::numeric_limits<float>::infinity())) --last;
        spans[static_cast<std::size_t>(y)] = {first, last};
    }
    return spans;
}

// One pass over rows [y0, y1): out = filtered `in` along x or y, at the pixels that hit
// something. The others are left alone: filter() starts both buffers with the same light,
// and nothing ever writes those pixels, so they stay equal in both.
inline void pass(const Guides& g, const Span* spans, const float* in, float* out, int step, bool along_x, int y0,
                 int y1) {
    static constexpr float kH[3] = {3.0f / 8.0f, 1.0f / 4.0f, 1.0f / 16.0f};
    const int w = g.width, h = g.height;
    for (int y = y0; y < y1; ++y) {
        for (int x = spans[y].first; x <= spans[y].last; ++x) {
            const std::size_t p = static_cast<std::size_t>(y) * w + x;
            if (!(g.depth[p] < std::numeric_limits<float>::infinity())) continue;
            float sum[3] = {kH[0] * in[3 * p], kH[0] * in[3 * p + 1], kH[0] * in[3 * p + 2]};
            float weight = kH[0];
            for (int t = -2; t <= 2; ++t) {
                if (t == 0) continue;
                const int qx = along_x ? x + t * step : x, qy = along_x ? y : y + t * step;
                if (qx < 0 || qx >= w || qy < 0 || qy >= h) continue;
                const std::size_t q = static_cast<std::size_t>(qy) * w + qx;
                const float wq = kH[std::abs(t)] * edge_weight(g, p, q, std::abs(t) * step);
                sum[0] += wq * in[3 * q];
                sum[1] += wq * in[3 * q + 1];
                sum[2] += wq * in[3 * q + 2];
                weight += wq;
            }
            const float inv = 1.0f / weight;
            for (int c = 0; c < 3; ++c) out[3 * p + c] = sum[c] * inv;
        }
    }
}

}  // namespace detail

// Filters `light` (3 floats per pixel) in place, on the pool's lanes. Only the rows' runs
// of hit pixels are visited: an overview's background (four fifths of the 10^8 plant's
// 720p frame) used to be copied from buffer to buffer in every pass.
inline void filter(const Guides& g, std::vector<float>& light, unsigned threads) {
    std::vector<float> tmp(light);
    const std::vector<detail::Span> spans = detail::hit_spans(g);
    constexpr int kRows = 16;
    const auto chunks = static_cast<std::size_t>((g.height + kRows - 1) / kRows);
    for (const int step : {1, 2, 4}) {
        for (const bool along_x : {true, false}) {
            const float* in = along_x ? light.data() : tmp.data();
            float* out = along_x ? tmp.data() : light.data();
            ThreadPool::global().parallel_for(chunks, [&](std::size_t c, unsigned) {
                const int y0 = static_cast<int>(c) * kRows;
                detail::pass(g, spans.data(), in, out, step, along_x, y0, std::min(g.height, y0 + kRows));
            }, threads);
        }
    }
}

}  // namespace denoise
VASTRAY_KERNEL_END
