"""Where a model's bytes go: node levels and each section of the triangle blocks.

Not a test. For each built model (or input, built first with the options given) this
reads every block and splits its bytes by what they hold: node levels, and in the
triangle blocks each section, raw and LZ4-compressed. Plain blocks (docs/FORMAT.md §11):
the 16-byte headers, list entries, triangle records, ids, colours and vertices. Compact
blocks (§11a): the 32-byte headers, leaf records (the lists), group headers, group data
(split into its corner, id and colour fields by their widths), palette and vertices.
A section's compressed share is that section compressed alone per block (LZ4 works on
the whole block, so the shares do not add up exactly to the stored size; the table gives
both). Also the duplication that inflates them: list entries and stored triangles per
triangle, vertices per stored triangle, and the bytes a stored vertex takes (12 as f32;
with quantized vertices the packed record's, FORMAT.md §11).

    python bench/bytes.py bench/.cache/plant-1e6-s1.ply ../shared/models/stanford-bunny.obj
    python bench/bytes.py --quantized-vertices --name bytes-qv MODELS...
    python bench/bytes.py --triangles plain MODELS...    # the plain triangle blocks
    python bench/bytes.py --tier-width 0 MODELS...   # untiered, to compare
    python bench/bytes.py --six-word-voxels MODELS...   # no packed voxels (FORMAT.md §10)
    python bench/bytes.py --padded-treelets MODELS...   # no packed treelets (FORMAT.md §7-8)
    python bench/bytes.py --layout smallest MODELS...   # a named layout (vastray/layouts.py)

A tiered model (FORMAT.md §15) stores a triangle once per tier block that references it,
so its stored triangles and vertices per triangle are higher: the *tiers* column says how
many tiers a level has.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import lz4.block
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from common import machine_info, markdown_table  # noqa: E402

from vastray.build import BuildOptions, build_model  # noqa: E402
from vastray.layouts import LAYOUTS, layout_options  # noqa: E402
from vastray.modelfile import COMPACT_GROUP, ModelFile  # noqa: E402

SECTIONS = ("header", "list", "triangles", "ids", "colours", "vertices")
# Compact blocks: their sections, and the group data's fields (raw bits, not separable
# for LZ4: a group's corners, ids and palette indices sit together).
COMPACT_SECTIONS = ("header", "records", "group headers", "group data", "palette", "vertices")
FIELDS = ("corners", "ids", "colours")


def _lz4(data: bytes) -> int:
    if not data:
        return 0
    return min(len(data), len(lz4.block.compress(data, mode="default", store_size=False)))


def group_fields(data: bytes, layout: dict[str, Any], has_colours: bool) -> dict[str, int]:
    """Bits of a compact block's group data by field (corners, ids, palette indices),
    from the widths in its group headers (FORMAT.md §11a)."""
    out = dict.fromkeys(FIELDS, 0)
    tris, width = layout["triangles_count"], layout["header_bits"]
    vertex_bits = (layout["vertices_count"] - 1).bit_length()
    words = np.frombuffer(data, np.uint8)
    for j in range(layout["group_count"]):
        pos = 8 * layout["groups"] + j * width
        n = min(COMPACT_GROUP, tris - COMPACT_GROUP * j)

        def field(at: int, w: int) -> int:
            start = at >> 3
            return (int.from_bytes(words[start : start + 9].tobytes(), "little") >> (at & 7)) & ((1 << w) - 1)

        data = 8 * (layout["data"] + field(pos, 16))
        pos += 16 + vertex_bits
        cw = field(pos, 5)
        out["corners"] += 3 * n * cw
        pos += 5 + layout["id_bits"]
        iw, split = field(pos, 6), field(pos + 6, 1)
        # split: a second base (6-bit width, then the distance) and a bit per id
        out["ids"] += 6 + field(data + 3 * n * cw, 6) + n * (iw + 1) if split else n * iw
        if has_colours:
            pos += 7 + (layout["palette_count"] - 1).bit_length()
            out["colours"] += n * field(pos, 5)
    return out


def breakdown(path: Path) -> dict[str, Any]:
    """Raw and compressed bytes per part of the file, and the duplication figures."""
    row: dict[str, Any] = {}
    with ModelFile(path) as m:
        compact = m.compact_triangles
        sections = COMPACT_SECTIONS if compact else SECTIONS
        raw = dict.fromkeys(sections, 0)
        packed = dict.fromkeys(sections, 0)
        fields = dict.fromkeys(FIELDS, 0)
        h = m.header
        tri_first, tri_count = m.levels[-1]
        node_blocks = m.blocks[:tri_first]
        row["node_raw"] = sum(e.raw_size for e in node_blocks)
        row["node_stored"] = sum(e.stored_size for e in node_blocks)
        row["tri_stored"] = sum(e.stored_size for e in m.blocks[tri_first:])
        row["index"] = h["data_offset"]
        row["parts"] = h["parts_size"]
        row["tiers"] = m.tier_count if m.tiered else 0
        # Voxel words (FORMAT.md §10): 1 per one-sample voxel, 6 per six-sample one, 4 if packed.
        row["voxel_raw"] = 4 * h["voxels_one"] + 24 * h["voxels_six"] - 8 * h["voxels_packed"]
        row["packed_share"] = h["voxels_packed"] / max(1, h["voxels_six"])
        entries = tris = verts = 0
        for b in range(tri_first, tri_first + tri_count):
            data = m.read_block(b)
            layout = m.triangle_layout(data)
            t, v = layout["triangles_count"], layout["vertices_count"]
            tris, verts = tris + t, verts + v
            if compact:
                keys = ("records", "groups", "data", "palette", "vertices", "end")
                cuts = [0, *[layout[k] for k in keys]]
                for name, bits in group_fields(data, layout, m.has_colours).items():
                    fields[name] += bits
            else:
                entries += layout["entries"]
                keys = ("triangles", "ids", "colours", "vertices", "end")
                cuts = [0, 16, *[layout[k] for k in keys]]
            for name, a, z in zip(sections, cuts[:-1], cuts[1:], strict=True):
                raw[name] += z - a
                packed[name] += _lz4(data[a:z])
        n = h["triangle_count"]
        if compact:  # every reference is one entry of a leaf record
            entries = h["references"]
        row.update(
            triangles=n, file=h["file_size"], blocks=tri_count, vertex_bytes=raw["vertices"] / max(1, verts),
            entries_per_tri=entries / n, stored_per_tri=tris / n, verts_per_stored=verts / max(1, tris),
            refs_per_tri=h["references"] / n,
        )  # fmt: skip
    row["compact"] = compact
    for name in sections:
        row[f"{name}_raw"] = raw[name]
        row[f"{name}_lz4"] = packed[name]
    for name in FIELDS if compact else ():
        row[f"{name}_bits"] = fields[name]
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("inputs", nargs="+", type=Path, help="built models (.vast) or inputs to build")
    ap.add_argument("--quantized-splits", action="store_true")
    ap.add_argument("--quantized-vertices", action="store_true")
    ap.add_argument("--tier-width", type=float, default=BuildOptions.tier_width, help="0: untiered")
    ap.add_argument("--traversal-cost", type=float, default=BuildOptions.traversal_cost)
    ap.add_argument(
        "--six-word-voxels",
        action="store_true",
        help="store every six-sample voxel in six words (no packed voxels), as version 5 did",
    )
    ap.add_argument(
        "--padded-treelets",
        action="store_true",
        help="treelets padded to 8 bytes, LOD words in 8-byte units (no packed treelets), as version 6 did",
    )
    ap.add_argument("--triangles", choices=("plain", "compact"), default=None,
                    help="triangle block layout (default: the builder's)")  # fmt: skip
    ap.add_argument("--layout", choices=list(LAYOUTS), default=None,
                    help="a named layout's options (vastray/layouts.py), not the flags above")  # fmt: skip
    ap.add_argument("--out", type=Path, default=HERE / "results")
    ap.add_argument("--name", default=None, help="write NAME.md to --out (default: print only)")
    args = ap.parse_args()
    info = machine_info({"command": "python bench/bytes.py " + " ".join(sys.argv[1:])})
    rows = []
    with tempfile.TemporaryDirectory(dir=HERE / ".cache" if (HERE / ".cache").exists() else None) as tmp:
        for src in args.inputs:
            path = src
            if src.suffix != ".vast":
                path = Path(tmp) / f"{src.stem}.vast"
                if args.layout:
                    fields = layout_options(args.layout)
                else:
                    fields = {
                        "quantized_splits": args.quantized_splits,
                        "quantized_vertices": args.quantized_vertices,
                        "tier_width": args.tier_width,
                        "traversal_cost": args.traversal_cost,
                    }
                    if args.triangles is not None:
                        fields["compact_triangles"] = args.triangles == "compact"
                opts = BuildOptions(
                    packed_voxels=not args.six_word_voxels,
                    packed_treelets=not args.padded_treelets,
                    overwrite=True,
                    **fields,
                )
                t0 = time.perf_counter()
                build_model(src, path, opts)
                print(f"{src.name}: built in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
            row = {"model": src.stem.removesuffix("-s1"), **breakdown(path)}
            rows.append(row)
            print(row, file=sys.stderr)
    compact = rows[0]["compact"]
    if any(r["compact"] != compact for r in rows):
        sys.exit("the models mix plain and compact triangle blocks: run them separately")
    sections = COMPACT_SECTIONS if compact else SECTIONS
    table = []
    for r in rows:
        n = r["triangles"]

        def bt(key: str, r: dict[str, Any] = r, n: int = n) -> str:
            return f"{r[key] / n:.2f}"

        table.append([
            r["model"], f"{n:,}", str(r["tiers"]), f"**{r['file'] / n:.2f}**", bt("node_raw"),
            bt("node_stored"), bt("voxel_raw"), f"{100 * r['packed_share']:.0f} %",
            *[f"{r[f'{s}_raw'] / n:.2f} / {r[f'{s}_lz4'] / n:.2f}" for s in sections],
            *[f"{r[f'{f}_bits'] / 8 / n:.2f}" for f in (FIELDS if compact else ())],
            bt("tri_stored"), f"{r['refs_per_tri']:.2f}", f"{r['entries_per_tri']:.2f}",
            f"{r['stored_per_tri']:.2f}", f"{r['verts_per_stored']:.2f}", f"{r['vertex_bytes']:.2f}",
        ])  # fmt: skip
    md = markdown_table(
        ["model", "triangles", "tiers", "**file B/tri**", "nodes raw", "nodes stored", "of which voxels raw",
         "six-sample voxels packed",
         *[f"{s} raw / lz4" for s in sections], *[f"{f} raw" for f in (FIELDS if compact else ())],
         "triangle blocks stored", "refs/tri", "list entries/tri",
         "stored tris/tri", "vertices/stored tri", "bytes/vertex"],
        table,
    )  # fmt: skip
    print(md)
    if args.name:
        flags = ("quantized_splits", "quantized_vertices", "six_word_voxels", "padded_treelets")
        flags = [f for f in flags if getattr(args, f)]
        if args.layout:
            kept = ("six_word_voxels", "padded_treelets")
            flags = [f"layout {args.layout}", *(f for f in flags if f in kept)]
        kind = "compact" if compact else "plain"
        text = [
            f"# Bytes per triangle by section ({', '.join(flags) or 'full precision'}; "
            f"{kind} triangle blocks)",
            "",
            "Every figure is bytes per kept triangle. A section's *lz4* figure is that section compressed "
            "alone, block by block; *triangle blocks stored* is what the file holds for them (LZ4 over whole "
            "blocks). *refs/tri* are leaf references per triangle, *stored tris/tri* triangle records "
            "(a triangle is stored once per block that references it), *bytes/vertex* the vertex "
            "section's raw bytes per stored vertex. *of which voxels raw*: the LOD voxels' share of the "
            "node levels (docs/FORMAT.md §10: 4 bytes for one sample, 24 for six, 16 packed)."
            + (
                " Compact blocks (docs/FORMAT.md §11a): *records* are the leaf lists, *group headers* the "
                "fixed-width header of each group of 8 triangles, *group data* their corner, id and colour "
                "fields, whose raw shares are the *corners / ids / colours raw* columns."
                if compact
                else ""
            ),
            "",
            "```sh",
            info["command"],
            "```",
            "",
            *[f"- {k}: {v}" for k, v in info.items() if k != "command"],
            "",
            md,
            "",
        ]
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"{args.name}.md").write_text("\n".join(text))


if __name__ == "__main__":
    main()
