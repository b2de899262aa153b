// Coarseness tiers (docs/FORMAT.md §15): the stream of its level that a unit of
// placement goes to. A unit is a sibling pair of treelets, or a leaf's triangles; its
// key is the enclosing radius R of the LOD node right above it, the node whose voxel a
// ray must refuse (R > t * cone) before it needs the unit. A view at distance t needs
// the units whose key is above t * cone, so units of equal key go together, coarsest
// first, and a far view reads only the first streams of each level.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "vastray/format.h"

namespace vastray::writer {

class Tiering {
public:
    // Untiered: every unit in tier 0 (a file without FLAG_TIERED).
    Tiering() = default;
    // Tier 0 holds every key >= R_root / 2^coarse_octaves (what any view of the whole
    // model needs); below that, a tier per `width` halvings of the key, the last tier
    // taking everything finer. A width of 0 or less: untiered.
    Tiering(float root_radius, double width, int coarse_octaves) {
        if (!(width > 0)) return;
        const double anchor = std::ldexp(static_cast<double>(root_radius), -coarse_octaves);
        bounds_.resize(format::kMaxTiers - 1);
        for (std::size_t t = 0; t < bounds_.size(); ++t) {
            bounds_[t] = anchor * std::exp2(-static_cast<double>(t) * width);
        }
    }

    bool enabled() const { return !bounds_.empty(); }

    // The tier of a unit whose LOD node above has radius `key` (infinity: no LOD node
    // above, the root treelet: tier 0). bounds_ falls: tier t holds [bounds_[t], bounds_[t-1]).
    std::uint32_t tier_of(float key) const {
        if (bounds_.empty()) return 0;
        const auto it = std::lower_bound(bounds_.begin(), bounds_.end(), static_cast<double>(key),
                                         [](double bound, double k) { return bound > k; });
        return static_cast<std::uint32_t>(it - bounds_.begin());
    }

private:
    std::vector<double> bounds_;
};

}  // namespace vastray::writer
