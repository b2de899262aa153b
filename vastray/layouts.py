"""Named build layouts: the BuildOptions a user picks by what the model file is for.

One definition for `vastray build --layout`, a build job's "layout" (the REST API, the
Python client) and the page's upload choice. Options given beside a layout override its
values. No imports of the builder: the CLI lists the names before it loads it.
"""

from __future__ import annotations

from typing import Any

# What each is measured to trade (docs/FORMAT.md, "Measured choices"):
# - balanced, the BuildOptions defaults: tiered blocks, so a far view reads the least;
# - smaller: compact triangle blocks, about 30 % smaller, lossless, full-detail frames a
#   few per cent slower;
# - smallest: also untiered, quantized vertices (lossy by at most one grid step), a
#   coarser tree and LZ4 HC 9: 34-39 % of balanced. The coarser tree's LOD frames are
#   slower at the same PoE but nearer full detail, and as fast at the same accuracy
#   (bench/results/tree-cost-accuracy-*.md); far views read more, and the build takes
#   longer (HC).
LAYOUTS: dict[str, dict[str, Any]] = {
    "balanced": {},
    "smaller": {"compact_triangles": True},
    "smallest": {
        "compact_triangles": True,
        "quantized_vertices": True,
        "tier_width": 0.0,
        "traversal_cost": 6.0,
        "lz4_hc_level": 9,
    },
}

# The BuildOptions fields a layout sets or a caller may set over it.
LAYOUT_FLAGS = (
    "quantized_splits",
    "quantized_vertices",
    "compact_triangles",
    "tier_width",
    "traversal_cost",
    "lz4_hc_level",
    "voxel_errors",
)


def layout_options(name: str) -> dict[str, Any]:
    """The BuildOptions fields layout `name` sets; ValueError naming the choices."""
    if name not in LAYOUTS:
        raise ValueError(f"unknown layout {name!r}: choose one of {', '.join(LAYOUTS)}")
    return dict(LAYOUTS[name])
