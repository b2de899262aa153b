// A thin layer over SSE, AVX and AVX-512 registers for the packet kernels: vfloat<W>
// holds W floats, vmask<W> W lane masks. W = 4 is SSE (VEX-encoded in the AVX builds),
// W = 8 is AVX (in the AVX, AVX2 and AVX-512 builds), W = 16 is AVX-512 (its build
// only; a mask there is a mask register). Only what the kernels use, each operation
// one instruction where the ISA has one. Comparisons follow C++ semantics on NaN
// (ordered, except != which is true for NaN), so a vector lane computes exactly what
// the scalar code computes for the same ray.
#pragma once

#include <immintrin.h>

#include <cstdint>
#include <cstring>

#include "vastray/isa.h"

VASTRAY_KERNEL_BEGIN
namespace simd {

#if VASTRAY_ISA_LEVEL >= VASTRAY_ISA_AVX512
constexpr int kWidth = 16;  // the widest float vector of this build
#elif VASTRAY_ISA_LEVEL >= VASTRAY_ISA_AVX
constexpr int kWidth = 8;
#else
constexpr int kWidth = 4;
#endif

// Operations are free functions, not friends: GCC 12 does not apply the target pragma
// to friends defined inside explicit specializations.
template <int W>
struct vfloat;
template <int W>
struct vmask;

template <>
struct vmask<4> {
    __m128 m;
    int bits() const { return _mm_movemask_ps(m); }
    static vmask from_bits(unsigned b) {
        const __m128i lanes = _mm_setr_epi32(1, 2, 4, 8);
        const __m128i set = _mm_and_si128(_mm_set1_epi32(static_cast<int>(b)), lanes);
        return {_mm_castsi128_ps(_mm_cmpeq_epi32(set, lanes))};
    }
};
inline vmask<4> operator&(vmask<4> a, vmask<4> b) { return {_mm_and_ps(a.m, b.m)}; }
inline vmask<4> operator|(vmask<4> a, vmask<4> b) { return {_mm_or_ps(a.m, b.m)}; }
inline vmask<4> operator^(vmask<4> a, vmask<4> b) { return {_mm_xor_ps(a.m, b.m)}; }
inline vmask<4> andnot(vmask<4> a, vmask<4> b) { return {_mm_andnot_ps(a.m, b.m)}; }  // b & ~a

template <>
struct vfloat<4> {
    __m128 v;
    static vfloat broadcast(float f) { return {_mm_set1_ps(f)}; }
    static vfloat load(const float* p) { return {_mm_loadu_ps(p)}; }
    static vfloat bits(std::uint32_t u) { return {_mm_castsi128_ps(_mm_set1_epi32(static_cast<int>(u)))}; }
    void store(float* p) const { _mm_storeu_ps(p, v); }
    float operator[](int i) const {
        alignas(16) float f[4];
        _mm_store_ps(f, v);
        return f[i];
    }
};
inline vfloat<4> operator+(vfloat<4> a, vfloat<4> b) { return {_mm_add_ps(a.v, b.v)}; }
inline vfloat<4> operator-(vfloat<4> a, vfloat<4> b) { return {_mm_sub_ps(a.v, b.v)}; }
inline vfloat<4> operator*(vfloat<4> a, vfloat<4> b) { return {_mm_mul_ps(a.v, b.v)}; }
inline vfloat<4> operator/(vfloat<4> a, vfloat<4> b) { return {_mm_div_ps(a.v, b.v)}; }
// min(a, b) = a < b ? a : b, which is std::min(b, a) (b when either is NaN); max alike.
inline vfloat<4> min(vfloat<4> a, vfloat<4> b) { return {_mm_min_ps(a.v, b.v)}; }
inline vfloat<4> max(vfloat<4> a, vfloat<4> b) { return {_mm_max_ps(a.v, b.v)}; }
inline vfloat<4> abs(vfloat<4> a) { return {_mm_andnot_ps(_mm_set1_ps(-0.0f), a.v)}; }
inline vfloat<4> sign_bits(vfloat<4> a) { return {_mm_and_ps(a.v, _mm_set1_ps(-0.0f))}; }
inline vfloat<4> operator^(vfloat<4> a, vfloat<4> b) { return {_mm_xor_ps(a.v, b.v)}; }
inline vmask<4> operator<(vfloat<4> a, vfloat<4> b) { return {_mm_cmplt_ps(a.v, b.v)}; }
inline vmask<4> operator<=(vfloat<4> a, vfloat<4> b) { return {_mm_cmple_ps(a.v, b.v)}; }
inline vmask<4> operator>(vfloat<4> a, vfloat<4> b) { return {_mm_cmpgt_ps(a.v, b.v)}; }
inline vmask<4> operator>=(vfloat<4> a, vfloat<4> b) { return {_mm_cmpge_ps(a.v, b.v)}; }
inline vmask<4> operator==(vfloat<4> a, vfloat<4> b) { return {_mm_cmpeq_ps(a.v, b.v)}; }
inline vmask<4> operator!=(vfloat<4> a, vfloat<4> b) { return {_mm_cmpneq_ps(a.v, b.v)}; }
// m ? a : b, lane by lane (bit patterns, so it also carries integer lanes).
inline vfloat<4> select(vmask<4> m, vfloat<4> a, vfloat<4> b) {
    return {_mm_or_ps(_mm_and_ps(m.m, a.v), _mm_andnot_ps(m.m, b.v))};
}

#if VASTRAY_ISA_LEVEL >= VASTRAY_ISA_AVX
template <>
struct vmask<8> {
    __m256 m;
    int bits() const { return _mm256_movemask_ps(m); }
    static vmask from_bits(unsigned b) {
        // AVX has no 256-bit integer compare: test the lane bits as floats.
        const __m256 lanes = _mm256_castsi256_ps(_mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128));
        const __m256 set = _mm256_and_ps(_mm256_castsi256_ps(_mm256_set1_epi32(static_cast<int>(b))), lanes);
        return {_mm256_cmp_ps(set, _mm256_setzero_ps(), _CMP_NEQ_UQ)};
    }
};
inline vmask<8> operator&(vmask<8> a, vmask<8> b) { return {_mm256_and_ps(a.m, b.m)}; }
inline vmask<8> operator|(vmask<8> a, vmask<8> b) { return {_mm256_or_ps(a.m, b.m)}; }
inline vmask<8> operator^(vmask<8> a, vmask<8> b) { return {_mm256_xor_ps(a.m, b.m)}; }
inline vmask<8> andnot(vmask<8> a, vmask<8> b) { return {_mm256_andnot_ps(a.m, b.m)}; }

template <>
struct vfloat<8> {
    __m256 v;
    static vfloat broadcast(float f) { return {_mm256_set1_ps(f)}; }
    static vfloat load(const float* p) { return {_mm256_loadu_ps(p)}; }
    static vfloat bits(std::uint32_t u) { return {_mm256_castsi256_ps(_mm256_set1_epi32(static_cast<int>(u)))}; }
    void store(float* p) const { _mm256_storeu_ps(p, v); }
    float operator[](int i) const {
        alignas(32) float f[8];
        _mm256_store_ps(f, v);
        return f[i];
    }
};
inline vfloat<8> operator+(vfloat<8> a, vfloat<8> b) { return {_mm256_add_ps(a.v, b.v)}; }
inline vfloat<8> operator-(vfloat<8> a, vfloat<8> b) { return {_mm256_sub_ps(a.v, b.v)}; }
inline vfloat<8> operator*(vfloat<8> a, vfloat<8> b) { return {_mm256_mul_ps(a.v, b.v)}; }
inline vfloat<8> operator/(vfloat<8> a, vfloat<8> b) { return {_mm256_div_ps(a.v, b.v)}; }
inline vfloat<8> min(vfloat<8> a, vfloat<8> b) { return {_mm256_min_ps(a.v, b.v)}; }
inline vfloat<8> max(vfloat<8> a, vfloat<8> b) { return {_mm256_max_ps(a.v, b.v)}; }
inline vfloat<8> abs(vfloat<8> a) { return {_mm256_andnot_ps(_mm256_set1_ps(-0.0f), a.v)}; }
inline vfloat<8> sign_bits(vfloat<8> a) { return {_mm256_and_ps(a.v, _mm256_set1_ps(-0.0f))}; }
inline vfloat<8> operator^(vfloat<8> a, vfloat<8> b) { return {_mm256_xor_ps(a.v, b.v)}; }
inline vmask<8> operator<(vfloat<8> a, vfloat<8> b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_LT_OQ)}; }
inline vmask<8> operator<=(vfloat<8> a, vfloat<8> b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_LE_OQ)}; }
inline vmask<8> operator>(vfloat<8> a, vfloat<8> b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_GT_OQ)}; }
inline vmask<8> operator>=(vfloat<8> a, vfloat<8> b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_GE_OQ)}; }
inline vmask<8> operator==(vfloat<8> a, vfloat<8> b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_EQ_OQ)}; }
inline vmask<8> operator!=(vfloat<8> a, vfloat<8> b) { return {_mm256_cmp_ps(a.v, b.v, _CMP_NEQ_UQ)}; }
inline vfloat<8> select(vmask<8> m, vfloat<8> a, vfloat<8> b) { return {_mm256_blendv_ps(b.v, a.v, m.m)}; }
#endif

#if VASTRAY_ISA_LEVEL >= VASTRAY_ISA_AVX512
template <>
struct vmask<16> {
    __mmask16 m;
    int bits() const { return static_cast<int>(m); }
    static vmask from_bits(unsigned b) { return {static_cast<__mmask16>(b)}; }
};
inline vmask<16> operator&(vmask<16> a, vmask<16> b) { return {_kand_mask16(a.m, b.m)}; }
inline vmask<16> operator|(vmask<16> a, vmask<16> b) { return {_kor_mask16(a.m, b.m)}; }
inline vmask<16> operator^(vmask<16> a, vmask<16> b) { return {_kxor_mask16(a.m, b.m)}; }
inline vmask<16> andnot(vmask<16> a, vmask<16> b) { return {_kandn_mask16(a.m, b.m)}; }  // b & ~a

template <>
struct vfloat<16> {
    __m512 v;
    static vfloat broadcast(float f) { return {_mm512_set1_ps(f)}; }
    static vfloat load(const float* p) { return {_mm512_loadu_ps(p)}; }
    static vfloat bits(std::uint32_t u) { return {_mm512_castsi512_ps(_mm512_set1_epi32(static_cast<int>(u)))}; }
    void store(float* p) const { _mm512_storeu_ps(p, v); }
    float operator[](int i) const {
        alignas(64) float f[16];
        _mm512_store_ps(f, v);
        return f[i];
    }
};
inline vfloat<16> operator+(vfloat<16> a, vfloat<16> b) { return {_mm512_add_ps(a.v, b.v)}; }
inline vfloat<16> operator-(vfloat<16> a, vfloat<16> b) { return {_mm512_sub_ps(a.v, b.v)}; }
inline vfloat<16> operator*(vfloat<16> a, vfloat<16> b) { return {_mm512_mul_ps(a.v, b.v)}; }
inline vfloat<16> operator/(vfloat<16> a, vfloat<16> b) { return {_mm512_div_ps(a.v, b.v)}; }
// (The masked forms with every lane set: GCC 12's _mm512_min_ps and _mm512_max_ps pass
// an undefined vector that -Wmaybe-uninitialized reports, GCC bug 105593.)
inline vfloat<16> min(vfloat<16> a, vfloat<16> b) { return {_mm512_mask_min_ps(a.v, 0xFFFF, a.v, b.v)}; }
inline vfloat<16> max(vfloat<16> a, vfloat<16> b) { return {_mm512_mask_max_ps(a.v, 0xFFFF, a.v, b.v)}; }
inline vfloat<16> abs(vfloat<16> a) { return {_mm512_andnot_ps(_mm512_set1_ps(-0.0f), a.v)}; }
inline vfloat<16> sign_bits(vfloat<16> a) { return {_mm512_and_ps(a.v, _mm512_set1_ps(-0.0f))}; }
inline vfloat<16> operator^(vfloat<16> a, vfloat<16> b) { return {_mm512_xor_ps(a.v, b.v)}; }
inline vmask<16> operator<(vfloat<16> a, vfloat<16> b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_LT_OQ)}; }
inline vmask<16> operator<=(vfloat<16> a, vfloat<16> b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_LE_OQ)}; }
inline vmask<16> operator>(vfloat<16> a, vfloat<16> b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_GT_OQ)}; }
inline vmask<16> operator>=(vfloat<16> a, vfloat<16> b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_GE_OQ)}; }
inline vmask<16> operator==(vfloat<16> a, vfloat<16> b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_EQ_OQ)}; }
inline vmask<16> operator!=(vfloat<16> a, vfloat<16> b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_NEQ_UQ)}; }
inline vfloat<16> select(vmask<16> m, vfloat<16> a, vfloat<16> b) { return {_mm512_mask_blend_ps(m.m, b.v, a.v)}; }
#endif

}  // namespace simd
VASTRAY_KERNEL_END
