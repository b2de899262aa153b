"""The `vastray` command line."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from vastray import __version__
from vastray.render import SHADING_MODES


def _cmd_render(args: argparse.Namespace) -> int:
    from PIL import Image

    from vastray.camera import Camera, frame_bounds, parse_size, parse_vec3
    from vastray.render import load_model, render

    width, height = parse_size(args.size)
    build_options = {"leaf_size": args.leaf_size, "threads": args.threads}
    model = load_model(
        args.model, on_phase=lambda phase: print(f"{phase} ...", file=sys.stderr, flush=True), **build_options
    )
    scene = model.scene
    stats = scene.build_stats
    print(
        f"model      {model.name}: {scene.triangle_count:,} triangles, "
        f"loaded in {model.load_seconds:.2f} s, kd-tree in {stats['build_ms'] / 1000:.2f} s "
        f"({stats['nodes']:,} nodes, depth {stats['max_depth']}, "
        f"{stats['memory_bytes'] / 2**20:.1f} MiB)"
    )
    lo, hi = scene.bounds
    if args.eye or args.target:
        framed = frame_bounds(lo, hi, fov=args.fov, width=width, height=height)
        camera = Camera(
            eye=parse_vec3(args.eye) if args.eye else framed.eye,
            target=parse_vec3(args.target) if args.target else framed.target,
            up=parse_vec3(args.up),
            fov=args.fov,
            width=width,
            height=height,
        )
    else:
        camera = frame_bounds(lo, hi, fov=args.fov, width=width, height=height, up=parse_vec3(args.up))
    frame = render(model, camera, shading=args.shading, ao_samples=args.ao_samples, threads=args.threads)
    Image.fromarray(frame.image).save(args.output)
    s = frame.stats
    ms = s["milliseconds"]
    mrays = s["rays"] / (ms / 1000.0) / 1e6 if ms > 0 else float("inf")
    primary = max(1, s["primary_rays"])
    print(
        f"render     {width}x{height} {args.shading}: {ms:.1f} ms, {s['rays']:,} rays "
        f"({mrays:.2f} Mrays/s on {s['threads']} threads), "
        f"{s['node_visits'] / primary:.1f} node visits and "
        f"{s['triangle_tests'] / primary:.1f} triangle tests per pixel"
    )
    print(
        f"camera     --eye {_fmt(camera.eye)} --target {_fmt(camera.target)} --up {_fmt(camera.up)} "
        f"--fov {camera.fov:g}"
    )
    print(f"wrote      {args.output}")
    return 0


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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vastray", description=__doc__)
    parser.add_argument("--version", action="version", version=f"vastray {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render a model to an image")
    r.add_argument("model", help="mesh file (OBJ/PLY/STL/GLB/OFF), 'demo', or scene:NAME[:TRIANGLES[:SEED]]")
    r.add_argument("-o", "--output", required=True, help="output image (PNG, JPEG, ...)")
    r.add_argument("--eye", help="camera position x,y,z (default: framed automatically)")
    r.add_argument("--target", help="point looked at x,y,z (default: the model's centre)")
    r.add_argument("--up", default="0,1,0", help="up vector x,y,z (default 0,1,0)")
    r.add_argument("--fov", type=float, default=45.0, help="vertical field of view in degrees")
    r.add_argument("--size", default="960x540", help="image size WIDTHxHEIGHT")
    r.add_argument("--shading", default="headlight", choices=SHADING_MODES)
    r.add_argument("--ao-samples", type=int, default=8, help="ambient-occlusion rays per pixel")
    r.add_argument("--threads", type=int, default=0, help="render threads (0: all cores)")
    r.add_argument("--leaf-size", type=int, default=2, help="kd-tree leaf size")
    r.set_defaults(func=_cmd_render)

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
    except (ValueError, OSError) as exc:
        # MeshError is a ValueError; the message names the file and the problem.
        print(f"vastray: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
