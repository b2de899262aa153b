// Runtime instruction-set dispatch (the Embree model): the ray-tracing kernels are
// compiled once per ISA level into their own namespace, and one of them is picked when
// the first frame is rendered: the best the CPU and OS support, or the one named by the
// environment variable VASTRAY_ISA (sse2, avx, avx2, avx512). The rest of the library is
// built for the portable baseline (x86-64 = SSE2), so one binary runs everywhere and
// still takes the fast path where there is one.
//
// How a kernel header or source keeps its ISA apart:
//
//   #include <...>                 // standard and shared headers first, outside
//   #include "vastray/isa.h"
//   VASTRAY_KERNEL_BEGIN           // namespace vastray { inline namespace isa_<X> {
//   ...kernel code...              // plus, in an ISA build, #pragma GCC target(...)
//   VASTRAY_KERNEL_END
//
// The inline namespace gives every function of an ISA build its own symbol, so the
// linker can never merge an AVX2 copy of a kernel into the SSE2 path. The target pragma
// (rather than -mavx2 on the whole file) keeps code from the standard library and the
// shared headers (vecmath.h, format.h, block_cache.h), which is included before the
// region, at the baseline ISA: their out-of-line copies are shared by all paths, and
// must run on every CPU. Inside the region they are still inlined (a baseline callee
// may be inlined into an AVX2 caller).
//
// Every kernel build uses the same float operations in the same order (no FMA
// contraction: -ffp-contract=off), so all paths give bit-identical frames.
#pragma once

#include <string>
#include <vector>

#if !defined(VASTRAY_ISA_LEVEL)
// The portable baseline: what every file outside the kernel builds is compiled for.
#define VASTRAY_ISA_LEVEL 1
#define VASTRAY_ISA_NS isa_sse2
#endif

#define VASTRAY_ISA_SSE2 1
#define VASTRAY_ISA_AVX 2
#define VASTRAY_ISA_AVX2 3
#define VASTRAY_ISA_AVX512 4

// AVX-512 is the x86-64-v4 set (F, BW, CD, DQ, VL) on top of AVX2's.
#if VASTRAY_ISA_LEVEL >= VASTRAY_ISA_AVX512
#define VASTRAY_ISA_TARGET_PUSH \
    _Pragma("GCC push_options") \
        _Pragma("GCC target(\"avx512f,avx512bw,avx512cd,avx512dq,avx512vl,avx2,fma,bmi,bmi2,popcnt\")")
#define VASTRAY_ISA_TARGET_POP _Pragma("GCC pop_options")
#elif VASTRAY_ISA_LEVEL >= VASTRAY_ISA_AVX2
#define VASTRAY_ISA_TARGET_PUSH _Pragma("GCC push_options") _Pragma("GCC target(\"avx2,fma,bmi,bmi2,popcnt\")")
#define VASTRAY_ISA_TARGET_POP _Pragma("GCC pop_options")
#elif VASTRAY_ISA_LEVEL >= VASTRAY_ISA_AVX
#define VASTRAY_ISA_TARGET_PUSH _Pragma("GCC push_options") _Pragma("GCC target(\"avx,popcnt\")")
#define VASTRAY_ISA_TARGET_POP _Pragma("GCC pop_options")
#else
#define VASTRAY_ISA_TARGET_PUSH
#define VASTRAY_ISA_TARGET_POP
#endif

#define VASTRAY_KERNEL_BEGIN VASTRAY_ISA_TARGET_PUSH namespace vastray { inline namespace VASTRAY_ISA_NS {
#define VASTRAY_KERNEL_END } } VASTRAY_ISA_TARGET_POP

namespace vastray {

enum class Isa {
    Sse2 = VASTRAY_ISA_SSE2,
    Avx = VASTRAY_ISA_AVX,
    Avx2 = VASTRAY_ISA_AVX2,
    Avx512 = VASTRAY_ISA_AVX512,
};

const char* isa_name(Isa isa);
// Paths this build has kernels for and this CPU (and OS) can run, slowest first.
std::vector<Isa> supported_isas();
// The path that runs: VASTRAY_ISA if set (std::invalid_argument for an unknown name,
// std::runtime_error for one this CPU cannot run), else the best supported. Chosen once.
Isa active_isa();

}  // namespace vastray
