// The kernels' one way to ask for a cache line ahead of use.
//
// A prefetch made with __builtin_prefetch has no side effect the compiler must keep. A
// helper that does nothing but prefetch is then free of side effects to GCC's
// interprocedural analysis, which drops the calls to it: GCC 12 did so to the in-core
// walks' vertex prefetch for two days of December 2026 (docs/native-core.md, "The vertex
// prefetches that were not there"), with the same answers and 10-19 % less speed. On
// x86 the prefetch here is a volatile asm statement, which the compiler keeps wherever it
// stands, so no helper built on it can vanish that way; tests/test_native_sources.py
// checks that the kernels prefetch through nothing else.
#pragma once

#include "vastray/isa.h"

VASTRAY_KERNEL_BEGIN

[[gnu::always_inline]] inline void prefetch_line(const void* p) {
#if defined(__x86_64__) || defined(__i386__)
    asm volatile("prefetcht0 %0" : : "m"(*static_cast<const char*>(p)));
#else
    __builtin_prefetch(p);
#endif
}

VASTRAY_KERNEL_END
