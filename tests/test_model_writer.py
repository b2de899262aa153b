"""What the model writer computes, beyond the layout: LOD voxel samples that follow the
surface (normal, colour) and respect occlusion, and output that does not depend on the
number of threads."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from modelwalk import decode_sample, walk

from vastray.build import BuildOptions, build_model
from vastray.camera import frame_bounds
from vastray.modelfile import ModelFile
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.renderer import PRIM_VOXEL

# 5-bit colour channels and 6-bit cube-face normal coordinates, plus averaging slack.
COLOUR_TOL = 1.0 / 31 + 1e-3
NORMAL_TOL = 0.05


def write_ply(path: Path, corners: np.ndarray, colours: np.ndarray) -> None:
    """Binary PLY, one vertex per corner, per-face RGB."""
    n = len(corners)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {3 * n}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {n}\nproperty list uchar int vertex_indices\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    faces = np.zeros(n, dtype=[("n", "u1"), ("v", "<i4", (3,)), ("rgb", "u1", (3,))])
    faces["n"] = 3
    faces["v"] = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
    faces["rgb"] = colours
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(corners.astype("<f4").reshape(-1, 3).tobytes())
        f.write(faces.tobytes())


def fan(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Corners and colours of a disc of `n` thin triangles around one vertex (a fine
    tessellation): no split can separate them near the centre, so some leaf holds more
    than a block fits."""
    angles = np.linspace(0.0, 2 * np.pi, n + 1)
    rim = np.stack([np.cos(angles), np.zeros_like(angles), np.sin(angles)], axis=1)
    corners = np.stack([np.zeros((n, 3)), rim[1:], rim[:-1]], axis=1)
    return corners, np.tile(np.array([90, 160, 90], np.uint8), (n, 1))


def grid_plane(size: float, cells: int, y: float) -> np.ndarray:
    """A square in the XZ plane at height y, split into 2 * cells^2 triangles."""
    t = np.linspace(-size / 2, size / 2, cells + 1)
    x0, z0 = np.meshgrid(t[:-1], t[:-1], indexing="ij")
    x1, z1 = x0 + (t[1] - t[0]), z0 + (t[1] - t[0])
    x0, z0, x1, z1 = (a.ravel() for a in (x0, z0, x1, z1))
    ys = np.full_like(x0, y)
    a = np.stack([x0, ys, z0], axis=1)
    b = np.stack([x1, ys, z0], axis=1)
    c = np.stack([x1, ys, z1], axis=1)
    d = np.stack([x0, ys, z1], axis=1)
    return np.concatenate([np.stack([a, b, c], axis=1), np.stack([a, c, d], axis=1)])


def lod_nodes(path: Path) -> list:
    with ModelFile(path) as model:
        return [n for n in walk(model) if n.kind == "lod"]


def test_voxels_of_a_flat_plane_are_one_sample_with_its_normal_and_colour(tmp_path: Path) -> None:
    corners = grid_plane(16.0, 48, 0.0)
    colour = np.array([200, 60, 30], dtype=np.uint8)
    write_ply(tmp_path / "plane.ply", corners, np.tile(colour, (len(corners), 1)))
    build_model(tmp_path / "plane.ply", tmp_path / "plane.vast")
    nodes = lod_nodes(tmp_path / "plane.vast")
    assert len(nodes) > 20
    for node in nodes:
        assert len(node.samples) == 1, "six faces of a flat patch say the same thing"
        c, n = decode_sample(node.samples[0])
        np.testing.assert_allclose(c, colour / 255.0, atol=COLOUR_TOL)
        assert abs(abs(n[1]) - 1.0) < NORMAL_TOL, f"voxel normal {n} is not the plane's (0, ±1, 0)"


@pytest.mark.parametrize(
    "normal", [(0.8, 0.5, 0.33), (0.33, 0.8, 0.5), (0.5, 0.33, 0.8)], ids=["major-x", "major-y", "major-z"]
)
def test_rendered_voxels_show_their_decoded_normals(tmp_path: Path, normal: tuple[float, ...]) -> None:
    """A tilted plane whose normal has three different components, one per major axis of
    the sample's code: where a voxel stands in for the plane, the `normal` shading shows
    the normal that the independent decoder (modelwalk) reads from the model's samples,
    so the renderer's decode puts each component on its own axis."""
    n = np.array(normal) / np.linalg.norm(normal)
    t1 = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(t1, n)  # (t1, n, t2) is right-handed, as (x, y, z) is: windings stay
    flat = grid_plane(16.0, 48, 0.0)
    corners = flat[..., 0:1] * t1 + flat[..., 1:2] * n + flat[..., 2:3] * t2
    write_ply(tmp_path / "tilted.ply", corners, np.tile(np.array([200, 60, 30], np.uint8), (len(corners), 1)))
    build_model(tmp_path / "tilted.ply", tmp_path / "tilted.vast")
    samples = {s for node in lod_nodes(tmp_path / "tilted.vast") for s in node.samples}
    expected = [decode_sample(s)[1] for s in samples]
    with OutOfCoreModel(tmp_path / "tilted.vast", make_cache(64 << 20)) as model:
        camera = frame_bounds(*model.bounds, width=160, height=120, direction=tuple(n))
        frame = model.render_complete(camera, shading="normal", pixels_of_error=8.0)
    voxels = frame.prim == PRIM_VOXEL
    assert voxels.sum() > 200, "the view should show voxels standing in for the plane"
    colours = frame.image[voxels].astype(np.float64)
    shown = [(e + 1.0) * 0.5 * 255.0 for e in expected]
    nearest = np.min([np.abs(colours - c).max(axis=1) for c in shown], axis=0)
    assert nearest.max() <= 1.0, f"voxel pixels whose colour is no decoded normal: {(nearest > 1.0).sum()}"


def test_voxels_respect_occlusion_between_two_stacked_planes(tmp_path: Path) -> None:
    # Red below, blue above, wide and close together: the top levels split x and z and
    # keep cells that hold both planes. Looking up from below sees red, down from above
    # sees blue; an average of the two (ignoring occlusion) would be purple on both.
    red, blue = np.array([220, 20, 20], np.uint8), np.array([20, 20, 220], np.uint8)
    low, high = grid_plane(16.0, 40, 0.0), grid_plane(16.0, 40, 1.0)
    corners = np.concatenate([low, high])
    colours = np.concatenate([np.tile(red, (len(low), 1)), np.tile(blue, (len(high), 1))])
    write_ply(tmp_path / "planes.ply", corners, colours)
    build_model(tmp_path / "planes.ply", tmp_path / "planes.vast")
    with ModelFile(tmp_path / "planes.vast") as model:
        centre_y = model.header["centre"][1]
        nodes = [n for n in walk(model) if n.kind == "lod"]
    spanning = [n for n in nodes if n.lo[1] + centre_y <= 0.0 and n.hi[1] + centre_y >= 1.0]
    assert len(spanning) >= 4, "expected several voxels whose cells hold both planes"
    for node in spanning:
        assert len(node.samples) == 6
        below_colour, below_normal = decode_sample(node.samples[2])  # face -y: viewer below
        above_colour, above_normal = decode_sample(node.samples[3])  # face +y: viewer above
        np.testing.assert_allclose(below_colour, red / 255.0, atol=COLOUR_TOL)
        np.testing.assert_allclose(above_colour, blue / 255.0, atol=COLOUR_TOL)
        # Face samples are oriented towards their viewer.
        assert below_normal[1] < -1 + NORMAL_TOL and above_normal[1] > 1 - NORMAL_TOL


@pytest.mark.slow
@pytest.mark.parametrize("quantized", [False, True], ids=["full", "quantized-splits"])
@pytest.mark.parametrize("memory", [2 << 30, 5 << 20], ids=["in-core", "out-of-core"])
def test_output_does_not_depend_on_the_thread_count(
    models_folder: Path, tmp_path: Path, memory: int, quantized: bool
) -> None:
    source = models_folder / "stanford-bunny.obj"
    options = {"memory": memory, "quantized_splits": quantized}
    one = build_model(source, tmp_path / "one.vast", BuildOptions(threads=1, **options))
    two = build_model(source, tmp_path / "two.vast", BuildOptions(threads=2, **options))
    assert (one["incore_parts"] > 1) == (memory < 1 << 30)
    assert (tmp_path / "one.vast").read_bytes() == (tmp_path / "two.vast").read_bytes()
    assert two["triangles"] == one["triangles"] > 0


@pytest.mark.slow
def test_more_threads_than_cores_build_the_same_file(tmp_path: Path) -> None:
    # Oversubscribed, the kd build's subtrees are taken, offered on and stolen back by
    # several threads at once (a thread waiting for a subtree it offered builds others'
    # meanwhile), so the tasks nest in many orders; the file must not change.
    files = []
    for threads in (1, 3, 8):
        out = tmp_path / f"threads-{threads}.vast"
        build_model("scene:plant:200000:5", out, BuildOptions(threads=threads))
        files.append(out.read_bytes())
    assert files[0] == files[1] == files[2]


@pytest.mark.slow
def test_a_fan_too_big_for_one_block_continues_into_the_next(tmp_path: Path) -> None:
    # 20,000 thin triangles around one vertex: some leaf holds more than a 64 KB block fits.
    n = 20_000
    corners, colours = fan(n)
    write_ply(tmp_path / "fan.ply", corners, colours)
    report = build_model(tmp_path / "fan.ply", tmp_path / "fan.vast")
    assert report["triangles"] == n
    with ModelFile(tmp_path / "fan.vast") as model:
        leaves = [node for node in walk(model) if node.kind == "leaf"]
        biggest = max(len(node.ids) for node in leaves)
        assert biggest > 2500, "the test needs a leaf larger than one triangle block"
        assert sorted({int(i) for node in leaves for i in node.ids}) == list(range(n))
        scene = model.to_scene()
    # Every triangle decodes to its input vertices, through the native decoder too.
    origins = np.column_stack([corners.mean(axis=1)[:, 0], np.full(n, 1.0), corners.mean(axis=1)[:, 2]])
    hits = scene.intersect(origins, np.tile([0.0, -1.0, 0.0], (n, 1)))
    assert (hits["prim"] == np.arange(n)).mean() > 0.999
