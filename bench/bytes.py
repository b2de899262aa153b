"""Where a model's bytes go: node levels and each section of the triangle blocks.

Not a test. For each built model (or input, built first with the options given) this
reads every block and splits its bytes by what they hold: node levels, and in the
triangle blocks the 16-byte headers, list entries, triangle records, ids, colours and
vertices (docs/FORMAT.md §11), raw and LZ4-compressed. A section's compressed share is
that section compressed alone per block (LZ4 works on the whole block, so the shares
do not add up exactly to the stored size; the table gives both). Also the duplication
that inflates them: list entries and stored triangles per triangle, vertices per stored
triangle, and the bytes a stored vertex takes (12 as f32; with quantized vertices the
packed record's, FORMAT.md §11).

    python bench/bytes.py bench/.cache/plant-1e6-s1.ply ../shared/models/stanford-bunny.obj
    python bench/bytes.py --quantized-vertices --name bytes-qv MODELS...
    python bench/bytes.py --tier-width 0 MODELS...   # untiered, to compare

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

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from common import machine_info, markdown_table  # noqa: E402

from vastray.build import BuildOptions, build_model  # noqa: E402
from vastray.modelfile import ModelFile  # noqa: E402

SECTIONS = ("header", "list", "triangles", "ids", "colours", "vertices")


def _lz4(data: bytes) -> int:
    if not data:
        return 0
    return min(len(data), len(lz4.block.compress(data, mode="default", store_size=False)))


def breakdown(path: Path) -> dict[str, Any]:
    """Raw and compressed bytes per part of the file, and the duplication figures."""
    raw = dict.fromkeys(SECTIONS, 0)
    packed = dict.fromkeys(SECTIONS, 0)
    row: dict[str, Any] = {}
    with ModelFile(path) as m:
        h = m.header
        tri_first, tri_count = m.levels[-1]
        node_blocks = m.blocks[:tri_first]
        row["node_raw"] = sum(e.raw_size for e in node_blocks)
        row["node_stored"] = sum(e.stored_size for e in node_blocks)
        row["tri_stored"] = sum(e.stored_size for e in m.blocks[tri_first:])
        row["index"] = h["data_offset"]
        row["parts"] = h["parts_size"]
        row["tiers"] = m.tier_count if m.tiered else 0
        entries = tris = verts = 0
        for b in range(tri_first, tri_first + tri_count):
            data = m.read_block(b)
            layout = m.triangle_layout(data)
            e, t, v = layout["entries"], layout["triangles_count"], layout["vertices_count"]
            entries, tris, verts = entries + e, tris + t, verts + v
            cuts = [
                0,
                16,
                layout["triangles"],
                layout["ids"],
                layout["colours"],
                layout["vertices"],
                layout["end"],
            ]
            for name, a, z in zip(SECTIONS, cuts[:-1], cuts[1:], strict=True):
                raw[name] += z - a
                packed[name] += _lz4(data[a:z])
        n = h["triangle_count"]
        row.update(
            triangles=n, file=h["file_size"], blocks=tri_count, vertex_bytes=raw["vertices"] / max(1, verts),
            entries_per_tri=entries / n, stored_per_tri=tris / n, verts_per_stored=verts / max(1, tris),
            refs_per_tri=h["references"] / n,
        )  # fmt: skip
    for name in SECTIONS:
        row[f"{name}_raw"] = raw[name]
        row[f"{name}_lz4"] = packed[name]
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("inputs", nargs="+", type=Path, help="built models (.vast) or inputs to build")
    ap.add_argument("--quantized-splits", action="store_true")
    ap.add_argument("--quantized-vertices", action="store_true")
    ap.add_argument("--tier-width", type=float, default=BuildOptions.tier_width, help="0: untiered")
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
                opts = BuildOptions(
                    quantized_splits=args.quantized_splits,
                    quantized_vertices=args.quantized_vertices,
                    tier_width=args.tier_width,
                    overwrite=True,
                )
                t0 = time.perf_counter()
                build_model(src, path, opts)
                print(f"{src.name}: built in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
            row = {"model": src.stem.removesuffix("-s1"), **breakdown(path)}
            rows.append(row)
            print(row, file=sys.stderr)
    table = []
    for r in rows:
        n = r["triangles"]

        def bt(key: str, r: dict[str, Any] = r, n: int = n) -> str:
            return f"{r[key] / n:.2f}"

        table.append([
            r["model"], f"{n:,}", str(r["tiers"]), f"**{r['file'] / n:.2f}**", bt("node_raw"),
            bt("node_stored"),
            *[f"{r[f'{s}_raw'] / n:.2f} / {r[f'{s}_lz4'] / n:.2f}" for s in SECTIONS],
            bt("tri_stored"), f"{r['refs_per_tri']:.2f}", f"{r['entries_per_tri']:.2f}",
            f"{r['stored_per_tri']:.2f}", f"{r['verts_per_stored']:.2f}", f"{r['vertex_bytes']:.2f}",
        ])  # fmt: skip
    md = markdown_table(
        ["model", "triangles", "tiers", "**file B/tri**", "nodes raw", "nodes stored",
         *[f"{s} raw / lz4" for s in SECTIONS], "triangle blocks stored", "refs/tri", "list entries/tri",
         "stored tris/tri", "vertices/stored tri", "bytes/vertex"],
        table,
    )  # fmt: skip
    print(md)
    if args.name:
        flags = [f for f in ("quantized_splits", "quantized_vertices") if getattr(args, f)]
        text = [
            f"# Bytes per triangle by section ({', '.join(flags) or 'full precision'})",
            "",
            "Every figure is bytes per kept triangle. A section's *lz4* figure is that section compressed "
            "alone, block by block; *triangle blocks stored* is what the file holds for them (LZ4 over whole "
            "blocks). *refs/tri* are leaf references per triangle, *stored tris/tri* triangle records "
            "(a triangle is stored once per block that references it), *bytes/vertex* the vertex "
            "section's raw bytes per stored vertex.",
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
