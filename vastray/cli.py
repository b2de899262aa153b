"""The `vastray` command line."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from typing import Any

from vastray import __version__
from vastray.camera import PROJECTIONS, STANDARD_VIEWS
from vastray.layouts import LAYOUTS
from vastray.renderer import SHADING_MODES


def _camera_from_args(
    args: argparse.Namespace,
    lo: Sequence[float],
    hi: Sequence[float],
    model_up: Sequence[float] | None = None,
) -> Any:
    """The camera the arguments describe; without --up, the model's up (else +y)."""
    from vastray.camera import Y_UP, parse_size, parse_vec3, resolve_camera

    width, height = parse_size(args.size)
    return resolve_camera(
        lo,
        hi,
        eye=parse_vec3(args.eye) if args.eye else None,
        target=parse_vec3(args.target) if args.target else None,
        up=parse_vec3(args.up) if args.up else model_up or Y_UP,
        view=args.view,
        fov=args.fov,
        width=width,
        height=height,
        projection=args.projection,
    )


def _print_render(camera: Any, shading: str, s: Any) -> None:
    ms = s.milliseconds
    mrays = s.rays / (ms / 1000.0) / 1e6 if ms > 0 else float("inf")
    primary = max(1, s.primary_rays)
    print(
        f"render     {camera.width}x{camera.height} {shading}: {ms:.1f} ms, {s.rays:,} rays "
        f"({mrays:.2f} Mrays/s on {s.threads} threads), "
        f"{s.node_visits / primary:.1f} node visits and "
        f"{s.triangle_tests / primary:.1f} triangle tests per pixel"
    )


def _build_walked_structures(scene: Any, shading: str) -> None:
    """Builds, and reports, what the frame's rays will walk (by the renderer's own rule,
    `Scene.walked_structures`; a frame's time never includes these first-use builds)."""
    walked = scene.walked_structures(shading)
    triangles = f"{scene.triangle_count:,} triangles"
    if walked["wide_bvh"]:
        print(f"building 8-wide BVH over {triangles} ...", file=sys.stderr, flush=True)
        wide = scene.any_hit_stats()
        print(
            f"wide BVH   8-wide BVH in {wide['build_ms'] / 1000:.2f} s ({wide['nodes']:,} nodes, "
            f"depth {wide['max_depth']}, {wide['memory_bytes'] / 2**20:.1f} MiB)"
        )
    if walked["kd_tree"]:
        print(f"building kd-tree over {triangles} ...", file=sys.stderr, flush=True)
        stats = scene.build_stats
        print(
            f"kd-tree    kd-tree in {stats['build_ms'] / 1000:.2f} s ({stats['nodes']:,} nodes, "
            f"depth {stats['max_depth']}, {stats['memory_bytes'] / 2**20:.1f} MiB with the geometry)"
        )


def _check_output(path: str) -> None:
    """Fail before rendering, not after, when the image cannot be written."""
    from PIL import Image

    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"{path}: no such directory {folder!r} for the output")
    if not os.access(folder, os.W_OK):
        raise PermissionError(f"{path}: cannot write into {folder!r}")
    ext = os.path.splitext(path)[1].lower()
    if ext not in Image.registered_extensions():
        raise ValueError(f"{path}: unknown image extension {ext!r} (use .png or .jpg)")


def _cmd_render(args: argparse.Namespace) -> int:
    from PIL import Image

    from vastray.outofcore import OutOfCoreModel, make_cache
    from vastray.render import SceneRenderer
    from vastray.renderer import open_renderer, render_params
    from vastray.units import parse_bytes

    # Everything that can be checked before loading and rendering is checked first.
    _check_output(args.output)
    _camera_from_args(args, (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)).validate()
    params = render_params(
        shading=args.shading, ao_samples=args.ao_samples, threads=args.threads, pixels_of_error=args.poe
    )
    if args.fetchers < 1:
        raise ValueError(f"--fetchers must be at least 1, got {args.fetchers}")
    if args.leaf_size < 1:
        raise ValueError(f"--leaf-size must be at least 1, got {args.leaf_size}")
    cache = make_cache(parse_bytes(args.cache, "cache budget"), args.fetchers)

    renderer = open_renderer(
        args.model,
        cache=cache,
        on_phase=lambda phase: print(f"{phase} ...", file=sys.stderr, flush=True),
        leaf_size=args.leaf_size,
        threads=args.threads,
    )
    try:
        if isinstance(renderer, OutOfCoreModel):
            print(
                f"model      {renderer.name}: {renderer.triangle_count:,} triangles, "
                f"{renderer.block_count:,} blocks ({renderer.file_size / 2**20:.1f} MiB), "
                f"opened in {renderer.open_seconds * 1000:.0f} ms; cache {args.cache}"
            )
        elif isinstance(renderer, SceneRenderer):
            print(
                f"model      {renderer.name}: {renderer.triangle_count:,} triangles, "
                f"loaded in {renderer.load_seconds + renderer.build_seconds:.2f} s"
            )
            _build_walked_structures(renderer.scene, args.shading)
        lo, hi = renderer.bounds
        camera = _camera_from_args(
            args, lo, hi, renderer.up if isinstance(renderer, OutOfCoreModel) else None
        )
        frame = renderer.render_complete(camera, params)
        Image.fromarray(frame.image).save(args.output)
        s = frame.stats
        _print_render(camera, args.shading, s)
        errors: list[str] = []
        if isinstance(renderer, OutOfCoreModel):
            print(
                f"detail     PoE {args.poe:g}: complete after {frame.frames} frame(s) "
                f"in {frame.seconds:.2f} s; "
                f"{s.voxel_hits:,} voxel hits, working set {s.working_set_bytes / 2**20:.1f} MiB "
                f"in {s.working_set_blocks:,} blocks"
            )
            errors = renderer.errors
            for error in errors:
                print(f"vastray: warning: {error} (drawn as the coarser voxels above it)", file=sys.stderr)
    finally:
        renderer.close()
    print(
        f"camera     --eye {_fmt(camera.eye)} --target {_fmt(camera.target)} --up {_fmt(camera.up)} "
        f"--fov {camera.fov:g}" + (" --projection orthographic" if camera.orthographic else "")
    )
    print(f"wrote      {args.output}")
    # Damaged blocks leave an image that is not full detail: say so in the exit status.
    return 3 if errors else 0


def _fmt(v: Sequence[float]) -> str:
    return ",".join(f"{x:.6g}" for x in v)


def _cmd_scene(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from vastray.scenes import write_scene

    triangles = int(float(args.triangles))
    with tqdm(total=triangles, unit="tri", unit_scale=True, desc=f"{args.name}", file=sys.stderr) as bar:
        info = write_scene(args.name, triangles, args.seed, args.output, progress=bar.update)
    print(
        f"wrote {args.output}: {info['triangles']:,} triangles, {info['vertices']:,} vertices, "
        f"{info['bytes'] / 2**20:.1f} MiB"
    )
    return 0


class _PhaseBars:
    """One tqdm bar per build phase, fed from BuildProgress events."""

    def __init__(self) -> None:
        self.phase = ""
        self.bar: Any = None

    def __call__(self, p: Any) -> None:
        from tqdm import tqdm

        if p.phase != self.phase:
            self.close()
            self.phase = p.phase
            unit = "B" if p.unit == "bytes" else "tri"
            self.bar = tqdm(total=p.total, unit=unit, unit_scale=True, desc=f"{p.phase:5}", file=sys.stderr)
        if self.bar.total != p.total:
            self.bar.total = p.total
        self.bar.update(p.done - self.bar.n)
        if p.message:
            self.bar.set_postfix_str(p.message, refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _cmd_build(args: argparse.Namespace) -> int:
    import signal
    import threading

    from vastray.build import (
        STATED_OVERHEAD_BYTES,
        BuildCancelledError,
        BuildOptions,
        build_model,
    )
    from vastray.camera import parse_vec3
    from vastray.layouts import LAYOUT_FLAGS, layout_options
    from vastray.units import parse_bytes

    # The layout's options, then each one given on the command line over them.
    layout = layout_options(args.layout)
    for name in LAYOUT_FLAGS:
        if getattr(args, name) is not None:
            layout[name] = getattr(args, name)
    options = BuildOptions(
        memory=parse_bytes(args.memory, "memory budget"),
        threads=args.threads,
        overwrite=args.force,
        scratch_dir=args.scratch_dir,
        up=parse_vec3(args.up) if args.up else None,
        **layout,
    )
    options.check()  # a bad option is a clear error before any work
    # Ctrl-C and SIGTERM (docker stop, kill) cancel the build: the builder checks the
    # event at every progress step and cleans up. (A KeyboardInterrupt raised wherever
    # the main thread happens to be, inside callbacks from native worker code, was not
    # reliably delivered.)
    cancel = threading.Event()
    received: list[int] = []

    def on_signal(signum: int, _frame: object) -> None:
        received.append(signum)
        cancel.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    bars = _PhaseBars()
    try:
        report = build_model(args.input, args.output, options, progress=bars, cancel=cancel)
    except BuildCancelledError:
        bars.close()
        print("vastray: interrupted; removed the partial model and scratch files", file=sys.stderr)
        return 128 + received[0] if received else 130
    finally:
        bars.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    phases = ", ".join(f"{k} {v:.1f} s" for k, v in report["phase_seconds"].items() if v >= 0.05)
    parts = f" in {report['input_parts']:,} named parts" if report["input_parts"] else ""
    stored = f", {report['parts']:,} parts stored" if report["parts"] else ""
    print(
        f"input      {report['input_triangles']:,} triangles{parts}; "
        f"{report['degenerate']:,} degenerate dropped (zero area or repeated corners)"
    )
    print(
        f"built      {report['output']}: {report['triangles']:,} triangles{stored} "
        f"in {report['seconds']:.1f} s "
        f"({report['input_triangles'] / max(1e-9, report['seconds']) / 1e6:.2f} Mtri/s; {phases})"
    )
    print(
        f"size       {report['file_bytes'] / 2**20:.1f} MiB, {report['bytes_per_triangle']:.1f} B/triangle, "
        f"compression {report['compression_ratio']:.2f}x, {report['blocks']:,} blocks, "
        f"{report['node_levels']} LOD levels"
    )
    print(f"layout     {args.layout}: {_describe_layout(options)}")
    print(
        f"memory     peak RSS {report['peak_rss_bytes'] / 2**20:.0f} MiB "
        f"(budget {options.memory / 2**20:.0f} MiB + {STATED_OVERHEAD_BYTES >> 20} MiB fixed overhead; "
        f"{report['incore_parts']} in-core part(s) of <= {report['incore_limit']:,} triangles)"
    )
    for warning in report["warnings"]:
        print(f"warning    {warning}")
    return 0


def _describe_layout(options: Any) -> str:
    """What a build's layout options made, in words (the layout's name alone would hide
    the options given over it)."""
    words = ["tiered" if options.tier_width > 0 else "untiered"]
    if options.tier_width > 0 and options.tier_width != 1:
        words[0] += f" ({options.tier_width:g} octaves per tier)"
    words.append("compact triangle blocks" if options.compact_triangles else "plain triangle blocks")
    quantized = {"splits": options.quantized_splits, "vertices": options.quantized_vertices}
    precision = [name for name, on in quantized.items() if on]
    words.append(f"quantized {' and '.join(precision)}" if precision else "full precision")
    words.append(f"traversal cost {options.traversal_cost:g}")
    words.append(f"LZ4 HC {options.lz4_hc_level}" if options.lz4_hc_level else "LZ4")
    if options.voxel_errors and options.quantized_splits:
        words.append("voxel errors")
    return ", ".join(words)


def _cmd_inspect(args: argparse.Namespace) -> int:
    import json

    from vastray.modelfile import ModelFile

    with ModelFile(args.model) as model:
        if args.verify:
            from tqdm import tqdm

            with tqdm(total=len(model.blocks), unit="block", desc="verify", file=sys.stderr) as bar:
                model.verify(progress=bar.update)
        stats = model.stats()
    if args.json:
        print(json.dumps(stats, indent=2))
        return 0
    lo, hi = stats["bounds"]
    splits = ", quantized splits" if stats.get("quantized_splits") else ""
    splits += " (packed treelets)" if stats.get("packed_treelets") else ""
    splits += ", voxel errors" if stats.get("voxel_errors") else ""
    splits += ", quantized vertices" if stats.get("quantized_vertices") else ""
    splits += f", {stats['tiers']} coarseness tiers" if stats.get("tiers") else ""
    splits += ", compact triangles" if stats.get("compact_triangles") else ""
    print(f"model      {stats['path']} (format version {stats['version']}{splits})")
    print(
        f"triangles  {stats['triangles']:,} (input {stats['input_triangles']:,}, "
        f"{stats['degenerate']:,} degenerate dropped), colours: {'yes' if stats['colours'] else 'no'}"
    )
    print(f"bounds     {_fmt(lo)} .. {_fmt(hi)}")
    print(f"up         {_fmt(stats['up']) if stats.get('up') else 'not said (taken as 0,1,0)'}")
    print(f"parts      {stats['part_count']:,}" + ("" if stats["part_count"] else " (the input named none)"))
    print(
        f"nodes      {stats['nodes']:,} ({stats['basic_nodes']:,} basic, {stats['lod_nodes']:,} LOD, "
        f"{stats['leaves']:,} leaves), {stats['references']:,} triangle references"
    )
    print(
        f"voxels     {stats['voxels']:,} "
        f"({stats['voxels_one']:,} one-sample, {stats['voxels_six']:,} six-sample, "
        f"{stats['voxels_packed']:,} of them packed)"
    )
    print(
        f"size       {stats['file_bytes'] / 2**20:.2f} MiB, {stats['bytes_per_triangle']:.1f} B/triangle, "
        f"{stats['blocks']:,} blocks, compression {stats['compression_ratio']:.2f}x"
    )
    print(
        f"{'LOD level':>10} {'nodes':>12} {'voxels':>12} {'blocks':>8} {'raw MiB':>10} "
        f"{'stored MiB':>11} {'ratio':>6}"
    )
    for lv in stats["levels"]:
        ratio = lv["raw_bytes"] / lv["stored_bytes"] if lv["stored_bytes"] else 1.0
        if lv["level"] == "triangles":
            counts = f"{lv['triangle_records']:>12,} {lv['vertices']:>12,}"
        else:
            counts = f"{lv['nodes']:>12,} {lv['voxels']:>12,}"
        print(
            f"{lv['level']!s:>10} {counts} {lv['blocks']:>8,} {lv['raw_bytes'] / 2**20:>10.2f} "
            f"{lv['stored_bytes'] / 2**20:>11.2f} {ratio:>6.2f}"
        )
        for tier in lv.get("tiers", []):
            if not tier["blocks"]:
                continue
            tier_ratio = tier["raw_bytes"] / tier["stored_bytes"] if tier["stored_bytes"] else 1.0
            print(
                f"{'tier ' + str(tier['tier']):>10} {tier['items']:>12,} {tier['extra']:>12,} "
                f"{tier['blocks']:>8,} {tier['raw_bytes'] / 2**20:>10.2f} "
                f"{tier['stored_bytes'] / 2**20:>11.2f} {tier_ratio:>6.2f}"
            )
    print("(triangle level: triangle records and vertices, counted once per block that stores them)")
    if stats.get("tiers"):
        print(
            "(tiers: a level's blocks by the size of the LOD node above them; tier 0 is what any view of "
            "the whole model needs, each further tier what only nearer views need)"
        )
    if args.verify:
        print(f"verified   all {stats['blocks']:,} blocks (checksums and decompression)")
    return 0


def _cmd_serve(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from vastray.server import Settings, serve

    # Flags override VASTRAY_* environment variables, which override the defaults.
    given = {k: v for k, v in vars(args).items() if k in Settings.model_fields and v is not None}
    if args.api_key:
        given["api_keys"] = args.api_key
    if args.cors_origin:
        given["cors_origins"] = args.cors_origin
    if args.no_demo:
        given["demo"] = False
    try:
        settings = Settings(**given)
    except ValidationError as exc:
        from vastray.schemas import describe_errors

        raise ValueError(describe_errors(exc.errors())) from None  # type: ignore[arg-type]
    return serve(settings)


def _add_serve(sub: Any) -> None:
    v = sub.add_parser("serve", help="run the render server (REST API, streams, the viewer page)",
                       description="Run the render server. Every flag has a VASTRAY_* environment variable "
                       "(e.g. --cache: VASTRAY_CACHE); flags win.")  # fmt: skip
    v.add_argument(
        "--data", dest="data_dir", help="data directory: registry, models, uploads (default ./data)"
    )
    v.add_argument("--host", help="address to listen on (default 127.0.0.1; 0.0.0.0 for every interface)")
    v.add_argument("--port", type=int, help="port (default 8000; 0 picks a free one)")
    v.add_argument("--public-url", help="the URL people open, when behind a proxy")
    v.add_argument("--cache", help="block cache budget shared by every model and viewer (default 1G)")
    v.add_argument("--render-threads", type=int, help="threads per frame (default 0: every core)")
    v.add_argument("--fetchers", type=int, help="block fetcher threads (default 2)")
    v.add_argument("--render-workers", type=int, help="frames rendered or encoded at once "
                   "(default 2; half the cores on machines of 6 or more)")  # fmt: skip
    v.add_argument("--api-key", action="append", help="API key for write endpoints (repeatable; default: "
                   "a random key printed at start)")  # fmt: skip
    v.add_argument("--cors-origin", action="append", help="an origin allowed to call the API from a browser")
    v.add_argument("--upload-limit", help="largest upload (default 4G)")
    v.add_argument("--max-pixels", type=int, help="pixel budget of one image (default 3840x2160)")
    v.add_argument("--build-jobs", type=int, help="build jobs at once (default 1)")
    v.add_argument("--build-memory", help="memory budget of a build job (default 2G)")
    v.add_argument("--build-threads", type=int, help="threads per build job (default 0: every core)")
    v.add_argument("--no-demo", action="store_true", help="do not build the demo into a new data directory")
    v.set_defaults(func=_cmd_serve)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vastray", description=__doc__)
    parser.add_argument("--version", action="version", version=f"vastray {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render a model to an image")
    r.add_argument(
        "model",
        help="built model, mesh file (OBJ/PLY/STL/GLB/OFF), 'demo', or scene:NAME[:TRIANGLES[:SEED]]",
    )
    r.add_argument("-o", "--output", required=True, help="output image (PNG, JPEG, ...)")
    r.add_argument("--eye", help="camera position x,y,z (default: framed automatically)")
    r.add_argument("--target", help="point looked at x,y,z (default: the model's centre)")
    r.add_argument(
        "--up",
        help="up vector x,y,z (default: the model's, as 'vastray build --up' wrote it, else 0,1,0; "
        "the framed view turns with it)",
    )
    r.add_argument(
        "--view",
        choices=list(STANDARD_VIEWS),
        help="a standard view of the whole model, upright about its up (without --eye and --target)",
    )
    r.add_argument("--fov", type=float, default=45.0, help="vertical field of view in degrees")
    r.add_argument(
        "--projection",
        choices=list(PROJECTIONS),
        default="perspective",
        help="orthographic: parallel rays over the extent the perspective view has at the target "
        "(nothing is cut off by the eye)",
    )
    r.add_argument("--size", default="960x540", help="image size WIDTHxHEIGHT")
    r.add_argument("--shading", default="headlight", choices=SHADING_MODES)
    r.add_argument("--ao-samples", type=int, default=8, help="ambient-occlusion rays per pixel")
    r.add_argument("--threads", type=int, default=0, help="render threads (0: all cores)")
    r.add_argument("--leaf-size", type=int, default=2, help="kd-tree leaf size (meshes built in core)")
    r.add_argument(
        "--poe",
        type=float,
        default=0.0,
        help="built models: pixels of error the level of detail may show (default 0: full detail)",
    )
    r.add_argument("--cache", default="1G", help="built models: block cache budget, e.g. 512M (default 1G)")
    r.add_argument("--fetchers", type=int, default=2, help="built models: block fetcher threads (default 2)")
    r.set_defaults(func=_cmd_render)

    b = sub.add_parser("build", help="build the out-of-core model the server renders from")
    b.add_argument(
        "input",
        help="mesh file (OBJ, PLY, STL, OFF, glTF/GLB, raw .f32 soup; every format streams, any size), "
        "'demo', or scene:NAME[:TRIANGLES[:SEED]]",
    )
    b.add_argument("-o", "--output", required=True, help="model file to write (e.g. model.vast)")
    b.add_argument("--memory", default="2G", help="memory budget, e.g. 2G or 512M (default 2G)")
    b.add_argument("--threads", type=int, default=0, help="build threads (0: all cores)")
    b.add_argument("--force", action="store_true", help="replace the output if it exists")
    b.add_argument("--scratch-dir", help="where temporary files go (default: next to the output)")
    b.add_argument(
        "--up",
        help="which way is up in the mesh, x,y,z (e.g. 0,0,1 for a z-up scan or CAD export): kept in "
        "the model, so renders and the server frame it upright (default: not said, taken as +y)",
    )
    b.add_argument(
        "--layout",
        choices=list(LAYOUTS),
        default="balanced",
        help="what the file is for: balanced (the default: tiered, so far views read least), "
        "smaller (compact triangle blocks: about 30 %% smaller, lossless), smallest (also "
        "untiered, quantized vertices, a coarser tree and LZ4 HC 9: 34-39 %% of balanced, the "
        "same frame time for the same accuracy, far views read more, a slower build); the "
        "options below override it (docs/FORMAT.md, Measured choices)",
    )
    b.add_argument(
        "--quantized-splits",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="split planes on a 20-bit grid of their cell: 4-byte basic nodes, the same images "
        "(format version 3; docs/FORMAT.md); on unless --no-quantized-splits",
    )
    b.add_argument(
        "--quantized-vertices",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="vertices on a 2^21-step grid of the model's box, bit-packed per block: smaller, "
        "lossy by at most one grid step, watertight (docs/FORMAT.md; on in the smallest layout)",
    )
    b.add_argument(
        "--tier-width",
        type=float,
        default=None,
        metavar="OCTAVES",
        help="coarseness tiers: blocks hold data a view needs from about the same distance, so "
        "far views read less; a tier per this many halvings of the LOD radius (default 1; "
        "0: one stream per level, the layout of format version 4, and the smallest layout's)",
    )
    b.add_argument(
        "--compact-triangles",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="triangle blocks with bit-packed leaf lists, corners, ids and colours: about 30 %% "
        "smaller, lossless, full-detail frames 4-12 %% slower (format version 5; docs/FORMAT.md; "
        "on in the smaller and smallest layouts)",
    )
    b.add_argument(
        "--traversal-cost",
        type=float,
        default=None,
        metavar="COST",
        help="the kd-tree's SAH cost of a node step, in triangle tests (default 4, the smallest "
        "layout 6): higher builds a coarser tree, faster and smaller (6: about 1.3x and 15-20 %%); "
        "at the same PoE its LOD frames are slower and nearer full detail, at the same accuracy "
        "as fast (docs/FORMAT.md, Measured choices)",
    )
    b.add_argument(
        "--lz4-hc-level",
        type=int,
        default=None,
        metavar="LEVEL",
        help="compress blocks with LZ4 HC at this level (1-12) instead of LZ4's fast compressor "
        "(0, the default; the smallest layout 9): the same format, read as fast; at 9 about 6 %% "
        "smaller and a build 1.4-1.6x as long (docs/FORMAT.md, Measured choices)",
    )
    b.add_argument(
        "--voxel-errors",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="LOD nodes keep a bound on how far their voxel's box lies from its triangles, and "
        "the LOD test compares that instead of the box's radius: a box around a thin pipe stands "
        "in for it sooner; on unless --no-voxel-errors (format version 8, with quantized splits; "
        "at the same accuracy 0.61-0.85x the working set of the 10^8 plant's overview, docs/FORMAT.md)",
    )
    b.set_defaults(func=_cmd_build)

    i = sub.add_parser("inspect", help="print a built model's statistics")
    i.add_argument("model", help="model file written by 'vastray build'")
    i.add_argument("--verify", action="store_true", help="read and check every block")
    i.add_argument("--json", action="store_true", help="print the statistics as JSON")
    i.set_defaults(func=_cmd_inspect)

    _add_serve(sub)

    s = sub.add_parser("scene", help="generate a procedural test scene")
    s.add_argument("name", help="scene name: spheres, plant, mandelbulb")
    s.add_argument("--triangles", default="100000", help="approximate triangle count (e.g. 1e6)")
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("-o", "--output", required=True, help="output file (.ply or .stl)")
    s.set_defaults(func=_cmd_scene)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        print("vastray: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError, RuntimeError) as exc:
        # MeshError is a ValueError; the message names the file and the problem.
        print(f"vastray: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
