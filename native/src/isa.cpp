// Which ISA path runs (isa.h): what the CPU and OS support, what VASTRAY_ISA asks for.
#include "vastray/isa.h"

#include <cstdlib>
#include <iterator>
#include <mutex>
#include <stdexcept>

#include "vastray/kernels.h"

namespace vastray {

const char* isa_name(Isa isa) {
    switch (isa) {
        case Isa::Sse2: return "sse2";
        case Isa::Avx: return "avx";
        case Isa::Avx2: return "avx2";
        case Isa::Avx512: return "avx512";
    }
    return "sse2";
}

namespace {

constexpr Isa kAll[] = {Isa::Sse2, Isa::Avx, Isa::Avx2, Isa::Avx512};

bool cpu_runs(Isa isa) {
#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
    // libgcc's checks include the OS's support for saving the AVX registers (XCR0).
    __builtin_cpu_init();
    switch (isa) {
        case Isa::Sse2: return true;
        case Isa::Avx: return __builtin_cpu_supports("avx") && __builtin_cpu_supports("popcnt");
        case Isa::Avx2:
            return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") &&
                   __builtin_cpu_supports("bmi") && __builtin_cpu_supports("bmi2") && __builtin_cpu_supports("popcnt");
        case Isa::Avx512:
            // (libgcc also checks that the OS saves the mask and 512-bit registers.)
            return cpu_runs(Isa::Avx2) && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
                   __builtin_cpu_supports("avx512cd") && __builtin_cpu_supports("avx512dq") &&
                   __builtin_cpu_supports("avx512vl");
    }
#endif
    return isa == Isa::Sse2;
}

bool compiled(Isa isa) {
#if defined(VASTRAY_HAVE_AVX_KERNELS)
    (void)isa;
    return true;
#else
    return isa == Isa::Sse2;
#endif
}

std::string names(const std::vector<Isa>& isas) {
    std::string out;
    for (const Isa isa : isas) out += (out.empty() ? "" : ", ") + std::string(isa_name(isa));
    return out;
}

Isa choose() {
    const std::vector<Isa> usable = supported_isas();
    const char* forced = std::getenv("VASTRAY_ISA");
    if (forced == nullptr || *forced == '\0') return usable.back();
    const std::string name(forced);
    for (const Isa isa : kAll) {
        if (name != isa_name(isa)) continue;
        for (const Isa ok : usable) {
            if (ok == isa) return isa;
        }
        throw std::runtime_error("VASTRAY_ISA=" + name + ", but this " +
                                 (compiled(isa) ? "CPU" : "build") + " runs only " + names(usable));
    }
    throw std::invalid_argument("VASTRAY_ISA must be one of " + names({std::begin(kAll), std::end(kAll)}) +
                                " (got '" + name + "')");
}

}  // namespace

std::vector<Isa> supported_isas() {
    std::vector<Isa> out;
    for (const Isa isa : kAll) {
        if (compiled(isa) && cpu_runs(isa)) out.push_back(isa);
    }
    return out;
}

Isa active_isa() {
    // Chosen once; a bad VASTRAY_ISA is reported on every call until the process restarts.
    static std::once_flag once;
    static Isa chosen = Isa::Sse2;
    static std::string error;
    static bool invalid_name = false;
    std::call_once(once, [] {
        try {
            chosen = choose();
        } catch (const std::invalid_argument& e) {
            error = e.what();
            invalid_name = true;
        } catch (const std::runtime_error& e) {
            error = e.what();
        }
    });
    if (!error.empty()) {
        if (invalid_name) throw std::invalid_argument(error);
        throw std::runtime_error(error);
    }
    return chosen;
}

const KernelTable& kernels() {
    switch (active_isa()) {
#if defined(VASTRAY_HAVE_AVX_KERNELS)
        case Isa::Avx512: {
            // A kernel per path where paths differ, as Embree picks one per kernel: the
            // batch any-hit query walks the 8-wide BVH in 8-lane vectors on both AVX
            // levels, and its AVX-512 build (the same source, given 32 registers and
            // EVEX encodings) measured 0.85-0.96x the AVX2 one (docs/native-core.md).
            static const KernelTable table = [] {
                KernelTable t = kernel_table_avx512();
                t.occluded_scene = kernel_table_avx2().occluded_scene;
                return t;
            }();
            return table;
        }
        case Isa::Avx2: return kernel_table_avx2();
        case Isa::Avx: return kernel_table_avx();
#else
        case Isa::Avx512:
        case Isa::Avx2:
        case Isa::Avx:
#endif
        case Isa::Sse2: break;
    }
    return kernel_table_sse2();
}

}  // namespace vastray
