// An allocator for the in-core tree's big arrays (nodes, triangle lists, vertices) that
// puts them on 2 MiB transparent huge pages.
//
// A ray's walk touches a few nodes and vertices on pages scattered over the whole
// tree; once the tree is larger than the TLB's reach (a few MiB of 4 KiB pages) nearly
// every node load also waits for a page walk. Huge pages cut the TLB entries the tree
// needs by 512x: AO rays on the 10^7 plant ran 1.17-1.18x faster on them (measured with
// glibc's malloc.hugetlb tunable, docs/native-core.md). The block cache maps its slots
// with huge_pages::map too.
//
// Where the kernel runs transparent huge pages only for regions that ask
// ("madvise", the usual default), the region must ask before it is touched, so the
// allocator maps each large block itself, aligned to 2 MiB, and advises it first. Small
// blocks, and systems without MADV_HUGEPAGE, get ordinary memory.
#pragma once

#include <cstddef>
#include <cstdint>
#include <new>
#include <type_traits>
#include <vector>

#include <sys/mman.h>

namespace vastray {

namespace huge_pages {

constexpr std::size_t kHugePage = std::size_t{2} << 20;
// Below this a block stays on the heap: rounding it up to a huge page would waste more
// than its TLB entries cost.
constexpr std::size_t kThreshold = 4 * kHugePage;

inline std::size_t mapped_size(std::size_t bytes) { return (bytes + kHugePage - 1) / kHugePage * kHugePage; }

// A 2 MiB-aligned anonymous mapping of mapped_size(bytes) (mmap flags `extra` added,
// e.g. MAP_NORESERVE), advised for huge pages; nullptr when the system refuses the
// mapping. `advised`, if given, says whether the kernel took the advice. unmap() frees it.
inline void* map(std::size_t bytes, int extra = 0, bool* advised = nullptr) {
    const std::size_t size = mapped_size(bytes);
    // Over-map by one huge page and trim, so the kept range starts on a 2 MiB boundary.
    void* raw = mmap(nullptr, size + kHugePage, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS | extra, -1, 0);
    if (raw == MAP_FAILED) return nullptr;
    const auto base = reinterpret_cast<std::uintptr_t>(raw);
    const std::uintptr_t aligned = (base + kHugePage - 1) & ~(kHugePage - 1);
    if (aligned > base) munmap(raw, aligned - base);
    const std::uintptr_t end = aligned + size;
    const std::uintptr_t raw_end = base + size + kHugePage;
    if (raw_end > end) munmap(reinterpret_cast<void*>(end), raw_end - end);
    bool took = false;  // advice: a refusal leaves small pages
#ifdef MADV_HUGEPAGE
    took = madvise(reinterpret_cast<void*>(aligned), size, MADV_HUGEPAGE) == 0;
#endif
    if (advised) *advised = took;
    return reinterpret_cast<void*>(aligned);
}

inline void unmap(void* p, std::size_t bytes) { munmap(p, mapped_size(bytes)); }

}  // namespace huge_pages

// `huge` false: ordinary memory. The builder's trees want that (kdtree.h, KdBuildParams::
// huge_pages); the flag travels with the memory when a vector is moved.
template <class T>
struct HugePageAllocator {
    using value_type = T;
    using propagate_on_container_move_assignment = std::true_type;
    using propagate_on_container_copy_assignment = std::true_type;
    using propagate_on_container_swap = std::true_type;

    bool huge = true;

    HugePageAllocator() = default;
    explicit HugePageAllocator(bool use_huge_pages) : huge(use_huge_pages) {}
    template <class U>
    HugePageAllocator(const HugePageAllocator<U>& other) : huge(other.huge) {}

    T* allocate(std::size_t n) {
        if (n > static_cast<std::size_t>(-1) / sizeof(T)) throw std::bad_array_new_length();
        const std::size_t bytes = n * sizeof(T);
        if (!huge || bytes < huge_pages::kThreshold) {
            if constexpr (alignof(T) > __STDCPP_DEFAULT_NEW_ALIGNMENT__) {
                return static_cast<T*>(::operator new(bytes, std::align_val_t{alignof(T)}));
            } else {
                return static_cast<T*>(::operator new(bytes));
            }
        }
        void* p = huge_pages::map(bytes);
        if (!p) throw std::bad_alloc();
        return static_cast<T*>(p);
    }

    void deallocate(T* p, std::size_t n) {
        const std::size_t bytes = n * sizeof(T);
        if (!huge || bytes < huge_pages::kThreshold) {
            if constexpr (alignof(T) > __STDCPP_DEFAULT_NEW_ALIGNMENT__) {
                ::operator delete(p, std::align_val_t{alignof(T)});
            } else {
                ::operator delete(p);
            }
        } else {
            huge_pages::unmap(p, bytes);
        }
    }

    template <class U>
    bool operator==(const HugePageAllocator<U>& other) const {
        return huge == other.huge;
    }
    template <class U>
    bool operator!=(const HugePageAllocator<U>& other) const {
        return huge != other.huge;
    }
};

// A vector whose storage, once large, lies on huge pages.
template <class T>
using HugeVector = std::vector<T, HugePageAllocator<T>>;

}  // namespace vastray
