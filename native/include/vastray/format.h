// Bit layouts of the out-of-core model format (docs/FORMAT.md is the specification;
// this header is its single C++ transcription, shared by the writer and the readers).
//
// A model is a kd-tree cut into treelets of height 3. Treelets whose roots lie at depth
// 3k form LOD level k and are packed into 64 KB blocks of that level; leaf triangles
// live in triangle blocks, the last level. A tiered model (FLAG_TIERED) splits every
// level into streams by coarseness tier, so the data a far view needs is packed apart
// from what only a close view needs. Block ids stored in nodes are relative to the
// first block of the stream they point into, so streams can be written separately and
// concatenated without patching.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <vector>

#include "vastray/vecmath.h"

namespace vastray::format {

constexpr std::size_t kBlockSize = 64 * 1024;
constexpr int kTreeletHeight = 3;

// ---- the file: header and block index (docs/FORMAT.md §2-3) ---------------------------
// The Python writer (vastray/modelfile.py) takes these values from the native module,
// so the reader and the writer cannot disagree.
constexpr std::uint8_t kMagic[8] = {'V', 'A', 'S', 'T', 'R', 'A', 'Y', 0x1a};
constexpr std::uint32_t kVersion = 8;        // what the writer writes
constexpr std::uint32_t kOldestVersion = 1;  // still read: versions 1-7 are version 8 without its later additions
constexpr std::size_t kHeaderSize = 256;
constexpr std::size_t kHeaderCrcAt = 196;  // the header's own CRC-32 (zeroed while summing)
constexpr std::uint32_t kCodecStored = 0, kCodecLz4 = 1;
constexpr std::uint32_t kCodecFamilyLz4 = 1;  // the header's codec field
constexpr std::uint32_t kFlagColours = 1u << 0;
constexpr std::uint32_t kFlagTriangleIds = 1u << 1;
constexpr std::uint32_t kFlagPartIds = 1u << 2;  // the file ends in a parts section (version 2)
constexpr std::uint32_t kFlagQuantizedSplits = 1u << 3;  // 4-byte basic nodes, quantized splits (version 3)
constexpr std::uint32_t kFlagQuantizedVertices = 1u << 4;  // vertices on a grid of the root cell, bit-packed per block
constexpr std::uint32_t kFlagCompactTriangles = 1u << 5;  // compact triangle blocks (version 5, below)
constexpr std::uint32_t kFlagTiered = 1u << 6;  // levels split into streams by coarseness tier (version 5)
// Treelets on 4-byte boundaries and LOD words in 4-byte units (version 7, with
// kFlagQuantizedSplits only: their nodes are all multiples of 4 bytes), below.
constexpr std::uint32_t kFlagPackedTreelets = 1u << 7;
// LOD nodes carry a surface error beside their radius (version 8, with
// kFlagQuantizedSplits only: it takes the bits their split no longer needs), below.
constexpr std::uint32_t kFlagVoxelErrors = 1u << 8;
constexpr std::size_t kLevelRecord = 24, kEntryRecord = 24;
// The parts section (version 2): header fields at these offsets (zero without parts),
// then u32 part_count, u32 run_count, part records, runs and the names blob.
constexpr std::size_t kPartsOffsetAt = 200, kPartsSizeAt = 208, kPartsCrcAt = 216, kPartCountAt = 220;
constexpr std::size_t kPartsHead = 8, kPartRecord = 64, kRunRecord = 8;
constexpr std::uint32_t kNoPart = 0xFFFFFFFFu;  // a run of triangles in no part

// ---- coarseness tiers (version 5, FLAG_TIERED) -----------------------------------------
// The header's u32 at kTierCountAt is T, the tiers of every level (0 without the flag).
// The level table then has level_count * T records, level-major: record L * T + k is
// the stream of level L, tier k (tier 0 the coarsest), and the streams follow one
// another in that order in the file, empty ones included. A block reference in a node
// (a LOD node's child block word, a leaf's word 1) holds the tier in bits 26-31 and the
// block id relative to its stream's first block in bits 0-25. Untiered files are one
// stream per level, and their references are the whole 32-bit relative id.
constexpr std::size_t kTierCountAt = 224;
constexpr int kTierShift = 26;
constexpr std::uint32_t kMaxTiers = 1u << (32 - kTierShift);
constexpr std::uint32_t kMaxStreamBlocks = 1u << kTierShift;

inline std::uint32_t block_ref(std::uint32_t tier, std::uint32_t relative) { return (tier << kTierShift) | relative; }
inline std::uint32_t ref_tier(std::uint32_t ref, bool tiered) { return tiered ? ref >> kTierShift : 0u; }
inline std::uint32_t ref_relative(std::uint32_t ref, bool tiered) {
    return tiered ? ref & (kMaxStreamBlocks - 1) : ref;
}
// The record (and stream) index of level `level`, tier `tier` among `tiers` per level.
inline std::size_t stream_index(std::size_t level, std::uint32_t tier, std::uint32_t tiers) {
    return level * tiers + tier;
}

// ---- node word 0 ---------------------------------------------------------------------
// inner nodes (bit 31 set):  bits 0-1 split axis, bit 2 left child empty, bit 3 right
//                            child empty, bit 30 LOD node; word 1 split position (f32).
//   basic (8 B):  bits 4-9   right child offset from this node, 8-byte units
//                            (the left child, when present, follows directly).
//   LOD (16 B):   bits 4-10  voxel offset from this node, 4-byte units
//                 bits 11-16 right child treelet offset from the left one, 8-byte units
//                 bits 17-29 first present child treelet's offset in the child block,
//                            8-byte units
//                 word 2 enclosing-sphere radius (f32), word 3 the child block's
//                 reference (its stream of the next LOD level, and its id relative to
//                 the stream's first block; see the tiers above). With packed
//                 treelets (version 7) the offsets move and count in 4-byte units (below).
// leaf (8 B, bit 31 clear):  bits 0-15 first entry in the triangle block's list section,
//                            bits 16-30 triangle count; word 1 the triangle block's
//                            reference (a stream of the triangle level).
constexpr std::uint32_t kInner = 1u << 31;
constexpr std::uint32_t kLod = 1u << 30;
constexpr std::uint32_t kLeftEmpty = 1u << 2;
constexpr std::uint32_t kRightEmpty = 1u << 3;
constexpr std::uint32_t kMaxLeafTriangles = (1u << 15) - 1;

// ---- quantized split planes (version 3, FLAG_QUANTIZED_SPLITS; paper 004) --------------
// A basic node of a quantized model is 4 bytes: bits 0-3 as above, bits 4-9 the right
// child's offset in 4-byte units, bits 10-29 q, the split's position in its cell on the
// split axis in 2^20 steps: split = f32((lo * (2^20 - q) + hi * q) * 2^-20), evaluated
// in f64. Both products are exact in f64 (24-bit by at most 21-bit mantissas), so the
// one rounding of the sum is the same with or without fused multiply-add, in any
// reader; the result lies in [lo, hi]. The kd builder only places splits on these
// planes (and partitions by them), so the tree is exact: images do not change.
constexpr int kSplitBits = 20;
constexpr std::uint32_t kSplitSteps = 1u << kSplitBits;

inline float dequantize_split(float lo, float hi, std::uint32_t q) {
    const double a = static_cast<double>(lo) * static_cast<double>(kSplitSteps - q);
    const double b = static_cast<double>(hi) * static_cast<double>(q);
    return static_cast<float>((a + b) * (1.0 / static_cast<double>(kSplitSteps)));
}

// The plane of the grid of [lo, hi] nearest `target` (dir 0), or the nearest at or below
// it (dir < 0) or at or above it (dir > 0), strictly inside (lo, hi); false when the
// cell is too narrow for one. Monotone in q, so a few steps from the estimate settle it.
inline bool quantize_split(float lo, float hi, float target, int dir, std::uint32_t& q_out, float& split_out) {
    if (!(hi > lo) || !std::isfinite(lo) || !std::isfinite(hi)) return false;
    const double t = (static_cast<double>(target) - lo) / (static_cast<double>(hi) - lo) * kSplitSteps;
    long q = std::lround(std::clamp(t, 1.0, static_cast<double>(kSplitSteps - 1)));
    if (dir != 0) {
        for (int i = 0; i < 8 && q > 1 && dir < 0 && dequantize_split(lo, hi, static_cast<std::uint32_t>(q)) > target; ++i) --q;
        for (int i = 0; i < 8 && q < long{kSplitSteps - 1} && dir > 0 && dequantize_split(lo, hi, static_cast<std::uint32_t>(q)) < target; ++i) ++q;
    }
    const float s = dequantize_split(lo, hi, static_cast<std::uint32_t>(q));
    if (!(s > lo && s < hi)) return false;
    if ((dir < 0 && s > target) || (dir > 0 && s < target)) return false;
    q_out = static_cast<std::uint32_t>(q);
    split_out = s;
    return true;
}

// The q whose plane is exactly `split` in [lo, hi] (the writer's check that the builder
// put every split on the grid): the smallest q with dequantize_split >= split.
inline bool split_step(float lo, float hi, float split, std::uint32_t& q_out) {
    std::uint32_t a = 1, b = kSplitSteps - 1;
    while (a < b) {
        const std::uint32_t m = a + (b - a) / 2;
        if (dequantize_split(lo, hi, m) < split) a = m + 1;
        else b = m;
    }
    if (dequantize_split(lo, hi, a) != split) return false;
    q_out = a;
    return true;
}

// A quantized model's LOD nodes are 12 bytes: word 0, the split (f32) and the child
// block id; the enclosing-sphere radius is not stored but derived from the cell, which
// a reader of such a model carries anyway (full precision: 16 bytes, radius in word 2).
inline std::size_t lod_node_size(bool quantized) { return quantized ? 12 : 16; }
inline std::size_t lod_child_block_at(bool quantized) { return quantized ? 8 : 12; }
inline float cell_radius(const Vec3f& extent) { return 0.5f * length(extent); }

inline std::uint32_t float_bits(float f) {
    std::uint32_t u;
    std::memcpy(&u, &f, sizeof u);
    return u;
}
inline float bits_float(std::uint32_t u) {
    float f;
    std::memcpy(&f, &u, sizeof f);
    return f;
}

inline std::uint32_t basic_word(int axis, std::uint32_t empty, std::uint32_t right_off8) {
    return kInner | static_cast<std::uint32_t>(axis) | empty | (right_off8 << 4);
}
inline std::uint32_t quantized_basic_word(int axis, std::uint32_t empty, std::uint32_t right_off4, std::uint32_t q) {
    return kInner | static_cast<std::uint32_t>(axis) | empty | (right_off4 << 4) | (q << 10);
}
inline std::uint32_t lod_word(int axis, std::uint32_t empty, std::uint32_t voxel_off4,
                              std::uint32_t right_from_left8, std::uint32_t child_off8) {
    return kInner | kLod | static_cast<std::uint32_t>(axis) | empty | (voxel_off4 << 4) |
           (right_from_left8 << 11) | (child_off8 << 17);
}
inline std::uint32_t leaf_word(std::uint32_t first, std::uint32_t count) { return first | (count << 16); }

inline bool is_inner(std::uint32_t w) { return (w & kInner) != 0; }
inline bool is_lod(std::uint32_t w) { return (w & kLod) != 0; }
inline int axis_of(std::uint32_t w) { return static_cast<int>(w & 3u); }
inline std::uint32_t basic_right_off8(std::uint32_t w) { return (w >> 4) & 63u; }
inline std::uint32_t basic_right_off4(std::uint32_t w) { return (w >> 4) & 63u; }  // quantized models
inline std::uint32_t basic_split_step(std::uint32_t w) { return (w >> 10) & (kSplitSteps - 1); }
inline std::uint32_t lod_voxel_off4(std::uint32_t w) { return (w >> 4) & 127u; }
inline std::uint32_t lod_right_from_left8(std::uint32_t w) { return (w >> 11) & 63u; }
inline std::uint32_t lod_child_off8(std::uint32_t w) { return (w >> 17) & 8191u; }

// ---- packed treelets (version 7, kFlagPackedTreelets) ----------------------------------
// In a quantized model every node and voxel is a multiple of 4 bytes, so treelets start
// on 4-byte boundaries, unpadded (an 8-byte boundary left 4 bytes of zeros after about
// half of them: 4-5 % of the node levels). A LOD word counts its offsets in 4-byte
// units: bits 4-8 the voxel offset (a voxel lies at most 21 words past its node), 9-14
// the right child treelet's offset from the left one (a quantized treelet is at most
// 156 bytes), 15-29 the first child treelet's offset in its block (64 KiB / 4 = 2^14).
constexpr int kPackedVoxelShift = 4, kPackedRightShift = 9, kPackedChildShift = 15;
constexpr std::uint32_t kPackedVoxelOffMax = 31, kPackedRightMax = 63, kPackedChildOffMax = 32767;
inline std::uint32_t packed_lod_word(int axis, std::uint32_t empty, std::uint32_t voxel_off4,
                                     std::uint32_t right_from_left4, std::uint32_t child_off4) {
    return kInner | kLod | static_cast<std::uint32_t>(axis) | empty | (voxel_off4 << kPackedVoxelShift) |
           (right_from_left4 << kPackedRightShift) | (child_off4 << kPackedChildShift);
}

// A LOD word's three offsets in bytes, in either layout.
struct LodOffsets {
    std::uint32_t voxel, right_from_left, first_child;
};
inline LodOffsets lod_offsets(std::uint32_t w, bool packed) {
    if (packed) {
        return {4 * ((w >> kPackedVoxelShift) & kPackedVoxelOffMax), 4 * ((w >> kPackedRightShift) & kPackedRightMax),
                4 * ((w >> kPackedChildShift) & kPackedChildOffMax)};
    }
    return {4 * lod_voxel_off4(w), 8 * lod_right_from_left8(w), 8 * lod_child_off8(w)};
}

// A LOD word with its first-child field set to `child_off` bytes, in either layout (the
// writer places a deferred unit's treelets after their parent's word is written).
inline std::uint32_t with_child_offset(std::uint32_t w, std::size_t child_off, bool packed) {
    if (packed) {
        return (w & ~(kPackedChildOffMax << kPackedChildShift)) |
               (static_cast<std::uint32_t>(child_off / 4) << kPackedChildShift);
    }
    return (w & ~(8191u << 17)) | (static_cast<std::uint32_t>(child_off / 8) << 17);
}

// ---- voxel errors (version 8, kFlagVoxelErrors) ----------------------------------------
// A LOD node's word 1 holds its split as a step of its cell's grid, as a quantized basic
// node does (bits 0-19), and an error code c (bits 20-27; bits 28-31 zero). The node's
// LOD test compares e = R * (c + 1) / 256 instead of its radius R: an upper bound on how
// far the voxel's box surface lies from the triangles it stands in for, or R when that
// is no smaller (c = 255; docs/FORMAT.md §8 and §15). (c + 1) / 256 is exact in f32, so
// e is one rounding of one product, the same in every reader, and e = R at c = 255.
constexpr int kErrorShift = kSplitBits, kErrorBits = 8;
constexpr std::uint32_t kErrorCodeMax = (1u << kErrorBits) - 1;
inline std::uint32_t lod_split_word(std::uint32_t step, std::uint32_t code) { return step | (code << kErrorShift); }
inline std::uint32_t lod_split_step(std::uint32_t word1) { return word1 & (kSplitSteps - 1); }
inline std::uint32_t lod_error_code(std::uint32_t word1) { return (word1 >> kErrorShift) & kErrorCodeMax; }
inline float lod_error(float radius, std::uint32_t code) {
    return radius * (static_cast<float>(code + 1) * (1.0f / 256.0f));
}
// Word 1 with anything in the bits above the code (a damaged node).
inline bool lod_split_word_overflows(std::uint32_t word1) { return (word1 >> (kErrorShift + kErrorBits)) != 0; }
// The smallest code whose error is at least `error` (kErrorCodeMax when none below is).
inline std::uint32_t lod_error_code_for(float radius, float error) {
    if (!(error < radius) || !(radius > 0)) return kErrorCodeMax;
    const double c = std::ceil(static_cast<double>(error) / static_cast<double>(radius) * 256.0) - 1.0;
    auto code = static_cast<std::uint32_t>(std::clamp(c, 0.0, static_cast<double>(kErrorCodeMax)));
    while (code < kErrorCodeMax && lod_error(radius, code) < error) ++code;
    return code;
}

inline std::uint32_t leaf_first(std::uint32_t w) { return w & 0xffffu; }
inline std::uint32_t leaf_count(std::uint32_t w) { return (w >> 16) & kMaxLeafTriangles; }

// ---- voxel shading samples (paper 000 Table 1) ----------------------------------------
// bits 0-4 red, 5-9 green, 10-14 blue; bit 15 normal sign, bits 16-17 normal axis,
// bits 18-23 u, 24-29 v (6-bit two's complement, the cube-face coordinates times 31);
// bit 31 set when the voxel has one sample (else six, in face order -x +x -y +y -z +z).
constexpr std::uint32_t kOneSample = 1u << 31;
// Bit 30 of a voxel's first word, bit 31 clear (version 6): a packed voxel, six faces in
// four words where they show at most two colours (docs/FORMAT.md §10):
//   word 0      colour A (bits 0-14), face 0's normal (bits 15-29), bit 30 set
//   words 1-3   a 96-bit little-endian field: the normals of faces 1-5 at bits 15(f-1),
//               colour B at bit 75, and at bit 90 + f a 1 where face f shows colour B
constexpr std::uint32_t kPackedVoxel = 1u << 30;
constexpr std::uint32_t kSampleColour = 0x7FFFu;  // bits 0-14: what a face shows besides its normal
constexpr int kSampleNormalShift = 15;

// The words a voxel takes (1, 4 or 6), from its first word.
inline int voxel_words(std::uint32_t first) { return first & kOneSample ? 1 : (first & kPackedVoxel ? 4 : 6); }

// Six face samples in the packed form, when they show at most two colours. Only bits
// 0-29 of each sample are kept.
inline bool pack_voxel(const std::uint32_t (&six)[6], std::uint32_t (&out)[4]) {
    const std::uint32_t a = six[0] & kSampleColour;
    std::uint32_t b = a, mask = 0;
    for (int f = 1; f < 6; ++f) {
        const std::uint32_t c = six[f] & kSampleColour;
        if (c == a) continue;
        if (b != a && c != b) return false;
        b = c;
        mask |= 1u << f;
    }
    // The field as a low u64 (words 1-2) and a high u32 (word 3).
    std::uint64_t lo = 0, hi = 0;
    auto put = [&](int at, std::uint64_t v) {
        if (at < 64) lo |= v << at;
        if (at + 15 > 64) hi |= at >= 64 ? v << (at - 64) : v >> (64 - at);
    };
    for (int f = 1; f < 6; ++f) put(15 * (f - 1), (six[f] >> kSampleNormalShift) & 0x7FFFu);
    put(75, b);
    hi |= static_cast<std::uint64_t>(mask) << (90 - 64);
    out[0] = a | (six[0] & (0x7FFFu << kSampleNormalShift)) | kPackedVoxel;
    out[1] = static_cast<std::uint32_t>(lo);
    out[2] = static_cast<std::uint32_t>(lo >> 32);
    out[3] = static_cast<std::uint32_t>(hi);
    return true;
}

// The sample (bits 0-29; a one-sample voxel's keeps its bit 31) that face `face` of the
// voxel whose words start at `p` shows.
inline std::uint32_t voxel_face_sample(const std::uint8_t* p, int face) {
    std::uint32_t w[4];
    std::memcpy(w, p, 4);
    if (w[0] & kOneSample) return w[0];
    if (!(w[0] & kPackedVoxel)) {
        std::memcpy(w, p + 4 * face, 4);
        return w[0];
    }
    std::memcpy(w + 1, p + 4, 12);
    const std::uint64_t lo = w[1] | static_cast<std::uint64_t>(w[2]) << 32, hi = w[3];
    auto field = [&](int at) -> std::uint32_t {  // 15 bits at `at`
        const std::uint64_t v = at >= 64 ? hi >> (at - 64) : (lo >> at) | (at > 49 ? hi << (64 - at) : 0);
        return static_cast<std::uint32_t>(v) & 0x7FFFu;
    };
    const std::uint32_t normal = face == 0 ? (w[0] >> kSampleNormalShift) & 0x7FFFu : field(15 * (face - 1));
    const std::uint32_t colour = (hi >> (90 - 64 + face)) & 1u ? field(75) : w[0] & kSampleColour;
    return colour | normal << kSampleNormalShift;
}

inline std::uint32_t pack_sample(const Vec3f& colour, const Vec3f& normal, bool one_sample) {
    auto q5 = [](float c) { return static_cast<std::uint32_t>(std::clamp(std::lround(c * 31.0f), 0L, 31L)); };
    std::uint32_t s = q5(colour.x) | (q5(colour.y) << 5) | (q5(colour.z) << 10);
    const float ax = std::abs(normal.x), ay = std::abs(normal.y), az = std::abs(normal.z);
    const int axis = ax >= ay && ax >= az ? 0 : (ay >= az ? 1 : 2);
    const float major = normal[axis];
    if (major != 0 && std::isfinite(major)) {
        const float inv = 1.0f / std::abs(major);
        auto q6 = [&](float c) {
            const long q = std::clamp(std::lround(c * inv * 31.0f), -31L, 31L);
            return static_cast<std::uint32_t>(q) & 63u;
        };
        s |= (major < 0 ? 1u : 0u) << 15;
        s |= static_cast<std::uint32_t>(axis) << 16;
        s |= q6(normal[(axis + 1) % 3]) << 18;
        s |= q6(normal[(axis + 2) % 3]) << 24;
    }
    if (one_sample) s |= kOneSample;
    return s;
}

inline void unpack_sample(std::uint32_t s, Vec3f& colour, Vec3f& normal) {
    colour = {static_cast<float>(s & 31u) / 31.0f, static_cast<float>((s >> 5) & 31u) / 31.0f,
              static_cast<float>((s >> 10) & 31u) / 31.0f};
    const int axis = static_cast<int>((s >> 16) & 3u) % 3;
    auto s6 = [](std::uint32_t v) { return static_cast<float>(static_cast<int>(v << 26) >> 26) / 31.0f; };
    const float major = (s >> 15) & 1u ? -1.0f : 1.0f, u = s6((s >> 18) & 63u), v = s6((s >> 24) & 63u);
    // Chosen by value, not stored at a computed index: reading back as a vector the
    // components just written one by one stalled on store forwarding, a third of the
    // shading's time in a 10^8 overview (6.0 % of its profile before, 4.2 % after).
    const Vec3f n = axis == 0 ? Vec3f(major, u, v) : axis == 1 ? Vec3f(v, major, u) : Vec3f(u, v, major);
    normal = normalize(n);
}

// ---- triangle blocks --------------------------------------------------------------------
// 16-byte header (u32 list entries, triangles, vertices, and a word that is 0, or with
// FLAG_QUANTIZED_VERTICES the vertex record's bits per axis), then the sections, each
// starting on a 4-byte boundary:
//   list       u16 per entry: triangle index in this block (leaves point into it)
//   triangles  3 x u16 per triangle: vertex indices in this block
//   ids        u32 per triangle: the input triangle index (for picking and checks)
//   colours    u32 per triangle, 0x00BBGGRR, only when the model has colours
//   vertices   3 x f32 per vertex, relative to the model centre; or, quantized, an
//              i32[3] grid origin and one packed record per vertex (below).

// ---- quantized watertight vertices (FLAG_QUANTIZED_VERTICES; paper 004) -----------------
// Every vertex lies on a grid of the root cell: on axis a, the multiples k * S[a] of a
// power of two S[a], the smallest (at least 2^-126) with 2^20 * S[a] > max(|lo[a]|,
// |hi[a]|); the builder keeps |k| < 2^20, so 2^21 steps span the cell (which holds 0: it
// is centred). It snaps the vertices before it builds the tree, so the tree is exact for
// the triangles as stored. A vertex is f32(k) * S wherever it is stored: f32(k) is exact
// (|k| < 2^24) and so is the product by a power of two, so every reader, with or without
// fused multiply-add, decodes the same f32 for a vertex shared by triangles in different
// blocks, and neighbours stay watertight.
// A block stores k as its origin (i32[3], the smallest k on each axis) plus per vertex
// the offsets packed into `record` bytes, little-endian: bits[0] bits of x, then bits[1]
// of y, then bits[2] of z (bits[a] = the bit length of the block's span on axis a, at
// most 21; header word 3 = bits[0] | bits[1] << 8 | bits[2] << 16). Each record is read
// as 8 bytes, so the section has 8 - record bytes of slack after the last one.
constexpr int kVertexGridBits = 20;  // |k| < 2^20
constexpr std::uint32_t kMaxVertexBits = kVertexGridBits + 1;

inline float grid_vertex(std::int32_t k, float step) { return static_cast<float>(k) * step; }

inline float vertex_grid_step(float lo, float hi) {
    const float m = std::max(std::abs(lo), std::abs(hi));
    int e = -126;
    if (m > 0 && std::isfinite(m)) {
        int c;
        std::frexp(m, &c);  // m = f * 2^c with f in [0.5, 1): 2^c > m
        e = std::max(e, c - kVertexGridBits);
    }
    return std::ldexp(1.0f, e);
}
inline Vec3f vertex_grid_steps(const Vec3f& lo, const Vec3f& hi) {
    return {vertex_grid_step(lo.x, hi.x), vertex_grid_step(lo.y, hi.y), vertex_grid_step(lo.z, hi.z)};
}

struct TriangleBlockLayout {
    std::size_t list = 16, triangles = 0, ids = 0, colours = 0, vertices = 0, end = 0;
    bool packed = false;         // quantized vertices
    std::uint32_t bits[3] = {};  // their bits per axis
    std::size_t record = 12;     // bytes per vertex

    static std::size_t pad4(std::size_t n) { return (n + 3) & ~std::size_t{3}; }
    // `packing`: header word 3 of a quantized block (bits per axis), or none.
    static TriangleBlockLayout of(std::size_t entries, std::size_t tris, std::size_t verts, bool has_colours,
                                  bool packed = false, std::uint32_t packing = 0) {
        TriangleBlockLayout l;
        l.triangles = l.list + pad4(2 * entries);
        l.ids = l.triangles + pad4(6 * tris);
        l.colours = l.ids + 4 * tris;
        l.vertices = l.colours + (has_colours ? 4 * tris : 0);
        l.end = l.vertices + 12 * verts;
        if (packed) {
            l.packed = true;
            for (int a = 0; a < 3; ++a) l.bits[a] = (packing >> (8 * a)) & 0xffu;
            l.record = (l.bits[0] + l.bits[1] + l.bits[2] + 7) / 8;
            l.end = l.vertices + 12 + pad4(l.record * verts + 8 - l.record);
            // A damaged word (over 21 bits on an axis): an end past any block.
            if ((packing >> 24) != 0 || std::max({l.bits[0], l.bits[1], l.bits[2]}) > kMaxVertexBits) l.end = ~std::size_t{0};
        }
        return l;
    }
    // The layout a block's 16-byte header gives.
    static TriangleBlockLayout read(const std::uint8_t* tb, bool has_colours, bool quantized_vertices) {
        std::uint32_t h[4];
        std::memcpy(h, tb, sizeof h);
        return of(h[0], h[1], h[2], has_colours, quantized_vertices, h[3]);
    }
    // Vertex i of the block at tb when it stores f32 vertices (not packed). Always
    // inlined: the kernels read it in their hot loops, and an out-of-line copy could be
    // the SSE2 core's (lod_detail::plain_vertex says why that costs).
    [[gnu::always_inline]] Vec3f float_vertex(const std::uint8_t* tb, std::size_t i) const {
        Vec3f v;
        std::memcpy(&v, tb + vertices + 12 * i, 12);
        return v;
    }
    // Vertex i of the block at tb: f32 as stored, or f32(origin + offset) * step.
    Vec3f vertex(const std::uint8_t* tb, std::size_t i, const Vec3f& steps) const {
        if (!packed) return float_vertex(tb, i);
        std::int32_t o[3];
        std::uint64_t w;
        std::memcpy(o, tb + vertices, 12);
        std::memcpy(&w, tb + vertices + 12 + record * i, 8);
        const auto field = [&](int a, std::uint32_t shift) {
            return o[a] + static_cast<std::int32_t>((w >> shift) & ((std::uint64_t{1} << bits[a]) - 1));
        };
        return {grid_vertex(field(0, 0), steps.x), grid_vertex(field(1, bits[0]), steps.y),
                grid_vertex(field(2, bits[0] + bits[1]), steps.z)};
    }
};

// ---- compact triangle blocks (version 5, FLAG_COMPACT_TRIANGLES) ----------------------
// The same content as above (leaf lists, triangles, ids, colours, shared vertices) in
// bit fields as narrow as each part of a block allows, still readable per triangle: a
// ray decodes only the triangles it tests, and a hit's id, corners and colour from its
// index in the block. Triangles are numbered in the order leaves first use them (as in
// the plain layout), so a leaf's triangles are mostly a run of new ones plus a few that
// earlier leaves of the block brought in, and triangles of neighbouring leaves, which
// sit close in the model, share groups whose bases and widths fit them.
//
//   header   32 bytes: u32 T (triangles), V (vertices), P (vertex packing, as above, or
//            0: f32 vertices), K (palette colours; 0 without FLAG_COLOURS), id_min (the
//            smallest id), id_bits (bit length of max id - id_min), groups (byte offset
//            of the group headers), palette (byte offset of the palette)
//   records  from byte 32 to `groups`: one leaf record per leaf (per block, for a leaf
//            that continues), each starting on a byte; the leaf node's first field is
//            its byte offset in the block
//   headers  one fixed-width header per group of kGroup triangles, back to back, then
//            zero bits to the next byte
//   data     one data record per group, each starting on a byte
//   palette  K x u32 0x00BBGGRR, in order of first use
//   vertices V x f32[3]; or quantized, i32[3] grid origin, V records of bx+by+bz bits
//            back to back (not rounded to bytes), then 8 zero bytes of slack
//
// Bit fields are little-endian: bit i of a field stream starting at byte s is bit i % 8
// of byte s + i / 8, and a field of w bits at bit b holds bits b ... b + w - 1.
//
// Leaf record: base (16 bits: the index of the first triangle this leaf brings into the
// block), w (5 bits, <= 16), partial (1 bit; when set, a 16-bit entry count follows,
// else the record holds all the leaf's entries not read yet), then per entry a bit
// `new`: set, the triangle is `next` (starting at base) and next += 1; clear, a w-bit
// distance d follows and the triangle is next - 1 - d. A leaf whose entries run out in
// a block continues with the record at byte 32 of the next triangle block.
//
// Group j holds triangles kGroup * j ... + n - 1, n = min(kGroup, T - kGroup * j). Its
// header, at bit j * E of the headers (E = 16 + bit_length(V - 1) + 5 + id_bits + 7,
// with colours + bit_length(K - 1) + 5), holds: the byte offset of its data record from
// the start of the data (16 bits); corner base (bit_length(V - 1) bits) and width cw (5
// bits, <= 16); id base (id_bits bits), width iw (6 bits, <= 32) and a `split` bit; with
// colours, palette base (bit_length(K - 1) bits) and width pw (5 bits, <= 16). Its data
// record holds n x 3 corners of cw bits (vertex = corner base + field, the triangle's
// corners in order); then the ids: n fields of iw bits (id = id_min + id base + field),
// or, split, a width dw (6 bits, <= 32), a distance of dw bits to a second base, and n
// fields of 1 + iw bits whose low bit picks the base (id = id_min + id base + (bit ?
// distance : 0) + field >> 1), for a group whose triangles come from two runs of ids
// far apart; and with colours n palette indices of pw bits (palette base + field). The
// data starts at the byte after the headers. A header's position follows from j alone,
// so a reader goes from a triangle's index to its corners in two loads.
namespace compact {
constexpr std::size_t kHeader = 32;
constexpr std::uint32_t kGroup = 8;
constexpr std::uint32_t kBaseBits = 16, kCountBits = 16, kWidthBits = 5, kIdWidthBits = 6;
constexpr std::uint32_t kMaxTriangles = (1u << kBaseBits) - 1;  // a record's base (up to T) is 16-bit
constexpr std::uint32_t kMaxVertices = 1u << 16;          // corner widths are at most 16
}  // namespace compact

inline std::uint32_t bit_length(std::uint64_t x) { return x ? 64u - static_cast<std::uint32_t>(__builtin_clzll(x)) : 0u; }

// The readers below run once per triangle a ray tests: always inlined, so each kernel
// ISA (isa.h) gets its own copy instead of a call into one shared build.
#define VASTRAY_HOT [[gnu::always_inline]] inline

// `width` (at most 57) bits at bit `bit` of the stream at p; reads the 8 bytes at
// p + bit / 8, so a stream needs that much readable memory after its last field.
VASTRAY_HOT std::uint64_t read_bits(const std::uint8_t* p, std::size_t bit, std::uint32_t width) {
    std::uint64_t w;
    std::memcpy(&w, p + (bit >> 3), 8);
    return (w >> (bit & 7u)) & ((std::uint64_t{1} << width) - 1);
}

// Appends fields to a stream that starts on a byte of `out` (the writer's side of
// read_bits); align() ends it on a byte boundary, zero-filling the last byte.
class BitWriter {
public:
    explicit BitWriter(std::vector<std::uint8_t>& out) : out_(out) {}
    ~BitWriter() { align(); }
    void put(std::uint64_t value, std::uint32_t width) {  // width <= 64
        if (width > 32) {
            put(value & 0xffffffffu, 32);
            put(value >> 32, width - 32);
            return;
        }
        acc_ |= (value & ((std::uint64_t{1} << width) - 1)) << held_;
        held_ += width;
        for (; held_ >= 8; held_ -= 8, acc_ >>= 8) out_.push_back(static_cast<std::uint8_t>(acc_));
    }
    void align() {
        if (held_ > 0) out_.push_back(static_cast<std::uint8_t>(acc_));
        acc_ = 0;
        held_ = 0;
    }

private:
    std::vector<std::uint8_t>& out_;
    std::uint64_t acc_ = 0;
    std::uint32_t held_ = 0;
};

// A view of a compact block, set by parse(). Its members (like Group's and
// CompactLeafRecord's) have no initialisers on purpose: the traversal makes one per leaf
// it opens, and zeroing them would cost plain-layout leaves too.
struct CompactTriangleBlock {
    const std::uint8_t* data;
    std::uint32_t tris, verts, palette_size, id_min, id_bits;
    std::size_t groups, group_data, palette, vertices, end;
    std::uint32_t vertex_bits, palette_bits, header_bits;  // group header fields, E in all
    bool packed;
    // Quantized vertices: bits per axis, their sum, the block's grid origin, and where
    // each axis's field sits in a record (shift and mask, for the traversal's decoding).
    std::uint32_t bits[3], record_bits;
    std::int32_t origin[3];
    std::uint32_t shifts[3];
    std::uint64_t masks[3];

    static std::size_t group_count(std::size_t tris) { return (tris + compact::kGroup - 1) / compact::kGroup; }
    static std::uint32_t header_width(std::uint32_t verts, std::uint32_t id_bits, bool has_colours, std::uint32_t colours) {
        return 16 + bit_length(verts - 1) + compact::kWidthBits + id_bits + compact::kIdWidthBits + 1 +
               (has_colours ? bit_length(colours - 1) + compact::kWidthBits : 0);
    }
    static std::size_t vertex_bytes(std::size_t verts, bool packed, std::uint32_t record_bits) {
        return packed ? 12 + (verts * record_bits + 7) / 8 + 8 : 12 * verts;
    }

    // The view of the block at tb, of `size` readable bytes (its raw size, or 64 KiB in
    // the cache); false when its header contradicts itself or does not fit `size`.
    VASTRAY_HOT static bool parse(const std::uint8_t* tb, std::size_t size, bool has_colours, bool quantized,
                                  CompactTriangleBlock& b) {
        if (size < compact::kHeader) return false;
        std::uint32_t h[8];
        std::memcpy(h, tb, sizeof h);
        b.data = tb;
        b.tris = h[0];
        b.verts = h[1];
        b.palette_size = h[3];
        b.id_min = h[4];
        b.id_bits = h[5];
        b.groups = h[6];
        b.palette = h[7];
        if (b.tris == 0 || b.tris > compact::kMaxTriangles || b.verts == 0 || b.verts > compact::kMaxVertices ||
            b.id_bits > 32 || (has_colours ? b.palette_size == 0 || b.palette_size > b.tris : b.palette_size != 0)) {
            return false;
        }
        b.packed = quantized;
        b.record_bits = 0;
        if (quantized) {
            for (int a = 0; a < 3; ++a) b.bits[a] = (h[2] >> (8 * a)) & 0xffu;
            if ((h[2] >> 24) != 0 || std::max({b.bits[0], b.bits[1], b.bits[2]}) > kMaxVertexBits) return false;
            b.record_bits = b.bits[0] + b.bits[1] + b.bits[2];
        } else if (h[2] != 0) {
            return false;
        }
        b.vertex_bits = bit_length(b.verts - 1);
        b.palette_bits = has_colours ? bit_length(b.palette_size - 1) : 0;
        b.header_bits = header_width(b.verts, b.id_bits, has_colours, b.palette_size);
        b.group_data = b.groups + (group_count(b.tris) * b.header_bits + 7) / 8;
        b.vertices = b.palette + 4 * std::size_t{b.palette_size};
        b.end = b.vertices + vertex_bytes(b.verts, b.packed, b.record_bits);
        if (b.groups < compact::kHeader || b.group_data > b.palette || b.end > size) return false;
        if (quantized) {
            std::memcpy(b.origin, tb + b.vertices, 12);
            for (int a = 0; a < 3; ++a) {
                b.shifts[a] = a == 0 ? 0 : b.shifts[a - 1] + b.bits[a - 1];
                b.masks[a] = (std::uint64_t{1} << b.bits[a]) - 1;
            }
        }
        return true;
    }

    // One group of triangles: where its data starts and how wide its fields are.
    struct Group {
        const std::uint8_t* at;
        std::uint32_t first, n;
        std::uint32_t corner_base, cw, id_base, iw, palette_base, pw;
        bool split;                  // two id bases
        std::uint32_t id_distance;   // the second one's distance from the first
        std::size_t ids, colours;    // bit offsets of the id fields and the palette fields
    };
    // Group j (< the group count); false when its widths are out of range. Its fields
    // then lie within 110 bytes of a data offset below 64 KiB, so reading them stays
    // within the block and the 64 KiB after it (the cache's spare slot); fits() says
    // whether they also end inside the data.
    VASTRAY_HOT bool group(std::uint32_t j, Group& g) const {
        std::size_t bit = std::size_t{j} * header_bits;
        const std::uint8_t* h = data + groups;
        auto field = [&](std::uint32_t width) {
            const auto v = static_cast<std::uint32_t>(read_bits(h, bit, width));
            bit += width;
            return v;
        };
        const std::size_t at = group_data + field(16);
        if (at >= palette) return false;
        g.at = data + at;
        g.first = j * compact::kGroup;
        g.n = std::min(compact::kGroup, tris - g.first);
        g.corner_base = field(vertex_bits);
        g.cw = field(compact::kWidthBits);
        g.id_base = field(id_bits);
        g.iw = field(compact::kIdWidthBits);
        g.split = field(1) != 0;
        g.palette_base = g.pw = g.id_distance = 0;
        if (palette_size != 0) {  // the model has colours
            g.palette_base = field(palette_bits);
            g.pw = field(compact::kWidthBits);
        }
        if (g.cw > 16 || g.iw > 32 || g.pw > 16) return false;
        g.ids = std::size_t{3} * g.cw * g.n;
        std::uint32_t id_field = g.iw;
        if (g.split) {
            const auto dw = static_cast<std::uint32_t>(read_bits(g.at, g.ids, compact::kIdWidthBits));
            if (dw > 32) return false;
            g.id_distance = static_cast<std::uint32_t>(read_bits(g.at, g.ids + compact::kIdWidthBits, dw));
            g.ids += compact::kIdWidthBits + dw;
            id_field += 1;
        }
        g.colours = g.ids + std::size_t{id_field} * g.n;
        return true;
    }
    bool fits(const Group& g) const {
        return static_cast<std::size_t>(g.at - data) + (g.colours + std::size_t{g.pw} * g.n + 7) / 8 <= palette;
    }
    // Triangle `local`'s three vertex indices (not checked against V), from the first
    // fields of its group's header alone (the path of every triangle a ray tests); false
    // when that group is damaged as group() would say.
    VASTRAY_HOT bool corners(std::uint32_t local, std::uint32_t v[3]) const {
        const std::uint32_t j = local / compact::kGroup;
        const std::uint64_t h = read_bits(data + groups, std::size_t{j} * header_bits, 16 + vertex_bits + compact::kWidthBits);
        const std::size_t at = group_data + (h & 0xffffu);
        const auto base = static_cast<std::uint32_t>(h >> 16) & ((1u << vertex_bits) - 1);
        const auto cw = static_cast<std::uint32_t>(h >> (16 + vertex_bits)) & 31u;
        if (cw > 16 || at >= palette) return false;
        const std::uint64_t w = read_bits(data + at, std::size_t{3} * cw * (local - j * compact::kGroup), 3 * cw);
        const std::uint64_t mask = (std::uint64_t{1} << cw) - 1;
        v[0] = base + static_cast<std::uint32_t>(w & mask);
        v[1] = base + static_cast<std::uint32_t>((w >> cw) & mask);
        v[2] = base + static_cast<std::uint32_t>((w >> (2 * cw)) & mask);
        return true;
    }
    // Triangle i of group g: its three vertex indices (not checked against V).
    VASTRAY_HOT void corners(const Group& g, std::uint32_t i, std::uint32_t v[3]) const {
        const std::uint64_t w = read_bits(g.at, std::size_t{3} * g.cw * i, 3 * g.cw);
        const std::uint64_t mask = (std::uint64_t{1} << g.cw) - 1;
        v[0] = g.corner_base + static_cast<std::uint32_t>(w & mask);
        v[1] = g.corner_base + static_cast<std::uint32_t>((w >> g.cw) & mask);
        v[2] = g.corner_base + static_cast<std::uint32_t>((w >> (2 * g.cw)) & mask);
    }
    VASTRAY_HOT std::uint32_t id(const Group& g, std::uint32_t i) const {
        if (!g.split) return id_min + g.id_base + static_cast<std::uint32_t>(read_bits(g.at, g.ids + std::size_t{g.iw} * i, g.iw));
        const std::uint64_t f = read_bits(g.at, g.ids + std::size_t{g.iw + 1} * i, g.iw + 1);
        return id_min + g.id_base + ((f & 1u) ? g.id_distance : 0u) + static_cast<std::uint32_t>(f >> 1);
    }
    // The palette index of triangle i of group g (not checked against K).
    std::uint32_t palette_index(const Group& g, std::uint32_t i) const {
        return g.palette_base + static_cast<std::uint32_t>(read_bits(g.at, g.colours + std::size_t{g.pw} * i, g.pw));
    }
    std::uint32_t colour(std::uint32_t index) const {
        std::uint32_t c;
        std::memcpy(&c, data + palette + 4 * std::size_t{index}, 4);
        return c;
    }
    // Vertex v (< V): f32 as stored, or f32(origin + offset) * step, as in the plain layout.
    VASTRAY_HOT Vec3f vertex(std::uint32_t v, const Vec3f& steps) const {
        Vec3f p;
        if (!packed) {
            std::memcpy(&p, data + vertices + 12 * std::size_t{v}, 12);
            return p;
        }
        const std::size_t bit = std::size_t{v} * record_bits;
        const std::uint8_t* at = data + vertices + 12 + (bit >> 3);
        const std::uint32_t s = static_cast<std::uint32_t>(bit & 7u);
        std::uint64_t w;
        std::memcpy(&w, at, 8);
        w >>= s;
        if (record_bits > 57) {
            // Such a record can straddle two 8-byte words. Whether it does varies from
            // vertex to vertex, so the second word is always read (the branch on the
            // block's record width is predictable): s = 0 shifts it out entirely.
            std::uint64_t hi;
            std::memcpy(&hi, at + 8, 8);
            w |= (hi << 1) << (63 - s);
        }
        const auto field = [&](int a) { return origin[a] + static_cast<std::int32_t>((w >> shifts[a]) & masks[a]); };
        return {grid_vertex(field(0), steps.x), grid_vertex(field(1), steps.y), grid_vertex(field(2), steps.z)};
    }
};

// Reads one leaf record of a compact block, entry by entry.
class CompactLeafRecord {
public:
    // The record at byte `at` of block b, for a leaf with `remaining` entries not read
    // yet; false when it lies outside the records or says more than `remaining`.
    VASTRAY_HOT bool open(const CompactTriangleBlock& b, std::uint32_t at, std::uint32_t remaining) {
        if (at < compact::kHeader || at >= b.groups) return false;
        p_ = b.data + at;
        limit_ = 8 * (b.groups - at);
        tris_ = b.tris;
        const std::uint64_t w = read_bits(p_, 0, compact::kBaseBits + compact::kWidthBits + 1 + compact::kCountBits);
        next_ = static_cast<std::uint32_t>(w & 0xffffu);
        width_ = static_cast<std::uint32_t>(w >> compact::kBaseBits) & 31u;
        const bool partial = (w >> (compact::kBaseBits + compact::kWidthBits)) & 1u;
        bit_ = compact::kBaseBits + compact::kWidthBits + 1 + (partial ? compact::kCountBits : 0);
        count_ = partial ? static_cast<std::uint32_t>(w >> (compact::kBaseBits + compact::kWidthBits + 1)) & 0xffffu
                         : remaining;
        return width_ <= 16 && count_ >= 1 && count_ <= remaining && bit_ <= limit_;
    }
    std::uint32_t count() const { return count_; }
    // Whether the last read ran past the records (else a failed next() pointed outside the block).
    bool overrun() const { return bit_ > limit_; }
    // The next entry's triangle index; false when the record is damaged there (it runs
    // past the records or points outside the block's triangles).
    VASTRAY_HOT bool next(std::uint32_t& local) {
        // Without branches on the flag: new and old entries mix unpredictably.
        const std::uint64_t w = read_bits(p_, bit_, 1 + width_);  // the flag and a distance
        const bool fresh = (w & 1u) != 0;
        const auto d = static_cast<std::uint32_t>(w >> 1);
        const std::uint32_t old = next_ - 1 - d;  // wraps past 0 when d >= next: caught below
        local = fresh ? next_ : old;
        next_ += fresh ? 1u : 0u;
        bit_ += fresh ? 1u : 1u + width_;
        return (fresh || d < next_) && local < tris_ && bit_ <= limit_;
    }

private:
    const std::uint8_t* p_;
    std::size_t bit_, limit_;
    std::uint32_t next_, width_, count_, tris_;
};

#undef VASTRAY_HOT
}  // namespace vastray::format
