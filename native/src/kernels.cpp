// The kernel table of one ISA build (compiled once per ISA level; see isa.h).
#include "vastray/kernels.h"

namespace vastray {

namespace {
constexpr KernelTable kTable = {static_cast<Isa>(VASTRAY_ISA_LEVEL), &render_scene, &render_model,
                                &intersect_model, &intersect_scene, &occluded_scene, &denoise_light};
}  // namespace

#if VASTRAY_ISA_LEVEL == VASTRAY_ISA_AVX512
const KernelTable& kernel_table_avx512() { return kTable; }
#elif VASTRAY_ISA_LEVEL == VASTRAY_ISA_AVX2
const KernelTable& kernel_table_avx2() { return kTable; }
#elif VASTRAY_ISA_LEVEL == VASTRAY_ISA_AVX
const KernelTable& kernel_table_avx() { return kTable; }
#else
const KernelTable& kernel_table_sse2() { return kTable; }
#endif

}  // namespace vastray
