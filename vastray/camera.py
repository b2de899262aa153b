"""Camera description (perspective or orthographic) shared by the CLI, the renderers and
the server."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from vastray import native

Vec3 = tuple[float, float, float]

# A three-quarter view from above: shows three faces of a box-like model, the usual
# default of CAD viewers.
DEFAULT_VIEW_DIRECTION: Vec3 = (1.0, 0.7, 1.3)
Y_UP: Vec3 = (0.0, 1.0, 0.0)


# Perspective: rays from the eye. Orthographic: parallel rays along the view, over the
# extent the perspective view has at the target (see Camera).
PROJECTIONS = ("perspective", "orthographic")


def check_projection(projection: str) -> None:
    if projection not in PROJECTIONS:
        raise ValueError(f"projection must be one of {', '.join(PROJECTIONS)}, not {projection!r}")


def box_corners(lo: Sequence[float], hi: Sequence[float]) -> np.ndarray:
    """The eight corners of the box [lo, hi], (8, 3) float64."""
    xs, ys, zs = zip(lo, hi, strict=True)
    return np.array([[x, y, z] for x in xs for y in ys for z in zs], dtype=np.float64)


def unit_up(up: Sequence[float]) -> Vec3:
    """`up` as a unit vector; a clear error for a zero or non-finite one."""
    a = np.asarray(up, dtype=np.float64)
    big = float(np.abs(a).max()) if a.shape == (3,) else math.nan
    if not (math.isfinite(big) and big > 0.0):
        raise ValueError("up must be a finite, non-zero 3-vector")
    a = a / big  # scaled first: the squares of huge components overflow
    a /= np.linalg.norm(a)
    return (float(a[0]), float(a[1]), float(a[2]))


# The standard views of CAD viewers, for a y-up model: where the eye lies from the
# model, and the screen's up (front: +z, right: +x; the top view has the front at the
# bottom of the screen, the bottom view at the top). They turn with the model's up; the
# page has the same table (client/web/js/camera.js STANDARD_VIEWS).
STANDARD_VIEWS: dict[str, tuple[Vec3, Vec3]] = {
    "iso": (DEFAULT_VIEW_DIRECTION, Y_UP),
    "front": ((0.0, 0.0, 1.0), Y_UP),
    "back": ((0.0, 0.0, -1.0), Y_UP),
    "left": ((-1.0, 0.0, 0.0), Y_UP),
    "right": ((1.0, 0.0, 0.0), Y_UP),
    "top": (Y_UP, (0.0, 0.0, -1.0)),
    "bottom": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
}


def turn_from_y(d: Sequence[float], up: Sequence[float]) -> Vec3:
    """`d`, a direction of a y-up model, for a model whose up is `up`: turned by the
    shortest rotation that takes +y to `up`."""
    u = np.asarray(unit_up(up))
    d_a = np.asarray(d, dtype=np.float64)
    y = np.array([0.0, 1.0, 0.0])
    c = float(y @ u)
    if c < -1.0 + 1e-12:  # upside down: half a turn about x
        r = np.array([d_a[0], -d_a[1], -d_a[2]])
    else:
        # Rodrigues' formula for the rotation about y x u by the angle between them.
        k = np.cross(y, u)
        r = d_a * c + np.cross(k, d_a) + k * (k @ d_a) / (1.0 + c)
    return (float(r[0]), float(r[1]), float(r[2]))


def view_direction(up: Sequence[float] = Y_UP) -> Vec3:
    """The default three-quarter view direction for a model whose up is `up`, so a z-up
    model is seen from its front (-y) and above, as a y-up one is from +z and above."""
    return turn_from_y(DEFAULT_VIEW_DIRECTION, up)


@dataclass(frozen=True)
class Camera:
    """A view. `fov` is vertical, in degrees. An orthographic camera looks along the
    view from every pixel, over the extent the perspective view has at the target
    (2 |target - eye| tan(fov/2) high), so moving the eye closer zooms in; its rays start
    behind the model (`ray_plane`), so the eye cuts nothing off."""

    eye: Vec3
    target: Vec3
    up: Vec3 = (0.0, 1.0, 0.0)
    fov: float = 45.0  # vertical, degrees
    width: int = 960
    height: int = 540
    projection: str = "perspective"

    @property
    def orthographic(self) -> bool:
        return self.projection == "orthographic"

    def to_native(self) -> native.Camera:
        """The camera the native renderers take (validated there)."""
        check_projection(self.projection)
        eye, target, up = list(self.eye), list(self.target), list(self.up)
        return native.Camera(eye, target, up, self.fov, self.width, self.height, self.orthographic)

    def validate(self) -> None:
        """ValueError with the reason for absurd values (NaN, eye == target, up parallel
        to the view, fov outside (0, 180), an image side outside 1..MAX_IMAGE_SIDE, an
        unknown projection)."""
        self.to_native().validate()

    def ray_plane(self, bounds: tuple[Sequence[float], Sequence[float]] | None = None) -> np.ndarray:
        """Where an orthographic camera's rays start: the centre of a plane across the
        view, through the eye, or as the renderers place it for a model with box `bounds`
        (lo, hi): a power of two behind the eye when some corner of the box lies behind
        the eye's plane (native CameraRays::start_behind)."""
        e = np.asarray(self.eye, dtype=np.float64)
        if bounds is None:
            return e
        w = self.basis()[0]
        behind = float(np.max((e - box_corners(*bounds)) @ w))
        if behind > 0 and math.isfinite(behind):
            return e - w * 2.0 ** math.ceil(math.log2(behind))
        return e

    def image_rays(
        self, points: np.ndarray, bounds: tuple[Sequence[float], Sequence[float]] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """World rays (origins, unit directions) through image points (x, y), in pixels
        from the top-left corner of the image: pixel (i, j)'s centre is (i + 0.5, j + 0.5).
        The same rays the renderers trace through those points (for an orthographic
        camera, give the model's box as `bounds` for the renderers' origins)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        w, right, upv = self.basis()
        sx = 2.0 * pts[:, 0] / self.width - 1.0
        sy = 1.0 - 2.0 * pts[:, 1] / self.height
        if self.orthographic:
            dist = float(np.linalg.norm(np.asarray(self.target, dtype=np.float64) - np.asarray(self.eye)))
            plane = self.ray_plane(bounds)
            origins = (
                plane[None, :] + sx[:, None] * (right * dist)[None, :] + sy[:, None] * (upv * dist)[None, :]
            )
            return origins, np.broadcast_to(w, origins.shape).copy()
        dirs = w[None, :] + sx[:, None] * right[None, :] + sy[:, None] * upv[None, :]
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        return np.broadcast_to(np.asarray(self.eye, dtype=np.float64), dirs.shape).copy(), dirs

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(forward, right scaled to the half-width, up scaled to the half-height)."""
        e = np.asarray(self.eye, dtype=np.float64)
        w = np.asarray(self.target, dtype=np.float64) - e
        w /= np.linalg.norm(w)
        u = np.cross(w, np.asarray(self.up, dtype=np.float64))
        u /= np.linalg.norm(u)
        v = np.cross(u, w)
        tan_half = math.tan(self.fov * 0.5 * math.pi / 180.0)
        return w, u * (tan_half * self.width / self.height), v * tan_half

    def primary_rays(
        self, bounds: tuple[Sequence[float], Sequence[float]] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Primary rays in pixel order (row by row, top row first), in float64 exactly as
        the native renderer computes them: pixel (x, y) looks along
        normalize(w + (2(x+.5)/W - 1) tan(fov/2) aspect u + (1 - 2(y+.5)/H) tan(fov/2) v)
        with w = normalize(target - eye), u = normalize(w x up), v = u x w.

        Returns (origins, directions), each (width * height, 3). For tools and tests that
        need the renderer's rays without rendering (batch queries, picking, comparisons).
        An orthographic camera's rays go through image_rays (give `bounds` as there)."""
        if self.orthographic:
            xs, ys = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
            return self.image_rays(np.stack([xs.ravel(), ys.ravel()], axis=1), bounds)
        e = np.asarray(self.eye, dtype=np.float64)
        w, right, upv = self.basis()
        sx = 2.0 * (np.arange(self.width, dtype=np.float64) + 0.5) / self.width - 1.0
        sy = 1.0 - 2.0 * (np.arange(self.height, dtype=np.float64) + 0.5) / self.height
        dirs = (
            w[None, None, :]
            + sx[None, :, None] * right[None, None, :]
            + sy[:, None, None] * upv[None, None, :]
        )
        dirs = dirs.reshape(-1, 3)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        return np.broadcast_to(e, dirs.shape).copy(), dirs


def frame_bounds(
    lo: Sequence[float],
    hi: Sequence[float],
    *,
    fov: float = 45.0,
    width: int = 960,
    height: int = 540,
    direction: Sequence[float] | None = None,
    up: Vec3 = Y_UP,
    view: str = "iso",
    projection: str = "perspective",
) -> Camera:
    """A camera that shows the whole bounding box, seen from `direction` (pointing from
    the model towards the eye; by default the standard `view` of a model whose up is
    `up`, the three-quarter one unless told otherwise): the eye backs off along that
    direction until all eight corners of the box project inside the frame, with a small
    margin (for an orthographic camera, until the image spans them at every depth)."""
    if view not in STANDARD_VIEWS:
        raise ValueError(f"no standard view {view!r} (one of {', '.join(STANDARD_VIEWS)})")
    check_projection(projection)
    if direction is None:
        direction = turn_from_y(STANDARD_VIEWS[view][0], up)
        if view != "iso":  # (the three-quarter view keeps the up as given)
            up = turn_from_y(STANDARD_VIEWS[view][1], up)
    if not 0.0 < fov < 180.0:
        raise ValueError("fov must be between 0 and 180 degrees (exclusive)")
    lo_a, hi_a = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    centre = (lo_a + hi_a) / 2.0
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    w = -d  # viewing direction
    up_a = np.asarray(up, dtype=np.float64)
    if not np.linalg.norm(up_a) > 0:
        raise ValueError("camera up vector has zero length")
    u = np.cross(w, up_a / np.linalg.norm(up_a))
    if np.linalg.norm(u) < 1e-9:
        raise ValueError("view direction is parallel to the up vector")
    u /= np.linalg.norm(u)
    v = np.cross(u, w)
    tan_v = math.tan(math.radians(fov) / 2.0)
    tan_h = tan_v * width / height
    p = box_corners(lo_a, hi_a) - centre
    # A corner at camera-space (x, y, z) is visible from distance D when
    # |x| <= tan_h * (D + z) and |y| <= tan_v * (D + z); orthographic, the image spans
    # D tan at every depth, so only |x| and |y| count.
    needed = np.maximum(np.abs(p @ u) / tan_h, np.abs(p @ v) / tan_v)
    if projection != "orthographic":
        needed -= p @ w
    extent = float(np.linalg.norm(hi_a - lo_a))
    distance = max(1.08 * float(needed.max()), 1e-9 * max(1.0, float(np.abs(centre).max())), 0.5 * extent)
    eye = centre + d * distance
    return Camera(
        eye=(float(eye[0]), float(eye[1]), float(eye[2])),
        target=(float(centre[0]), float(centre[1]), float(centre[2])),
        up=up,
        fov=fov,
        width=width,
        height=height,
        projection=projection,
    )


def resolve_camera(
    lo: Sequence[float],
    hi: Sequence[float],
    *,
    eye: Sequence[float] | None = None,
    target: Sequence[float] | None = None,
    up: Sequence[float] = (0.0, 1.0, 0.0),
    fov: float = 45.0,
    width: int = 960,
    height: int = 540,
    view: str | None = None,
    projection: str = "perspective",
) -> Camera:
    """The camera of a partial description, as the CLI and the server read one: without
    an eye it frames the model's box (lo, hi), from the standard `view` if one is named;
    a missing target is the box's centre seen from the framed direction, a missing eye
    the framed eye."""
    up3 = (float(up[0]), float(up[1]), float(up[2]))
    if view is not None:
        if eye is not None or target is not None:
            raise ValueError("a standard view frames the whole model: give it without an eye or a target")
        return frame_bounds(
            lo, hi, fov=fov, width=width, height=height, up=up3, view=view, projection=projection
        )
    framed = frame_bounds(lo, hi, fov=fov, width=width, height=height, up=up3, projection=projection)
    if eye is None and target is None:
        return framed
    e = framed.eye if eye is None else (float(eye[0]), float(eye[1]), float(eye[2]))
    t = framed.target if target is None else (float(target[0]), float(target[1]), float(target[2]))
    return Camera(eye=e, target=t, up=up3, fov=fov, width=width, height=height, projection=projection)


def parse_vec3(text: str) -> Vec3:
    """Parse 'x,y,z' into three finite floats."""
    parts = text.split(",")
    if len(parts) != 3:
        raise ValueError(f"expected three comma-separated numbers, got {text!r}")
    try:
        x, y, z = (float(p) for p in parts)
    except ValueError as exc:
        raise ValueError(f"not a number in {text!r}") from exc
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise ValueError(f"non-finite value in {text!r}")
    return (x, y, z)


def parse_size(text: str) -> tuple[int, int]:
    """Parse 'WxH' into positive integers."""
    try:
        w, h = (int(p) for p in text.lower().split("x"))
    except ValueError as exc:
        raise ValueError(f"expected WIDTHxHEIGHT, got {text!r}") from exc
    limit = native.MAX_IMAGE_SIDE
    if not (0 < w <= limit and 0 < h <= limit):
        raise ValueError(f"image size {text!r} out of range: each side must be 1..{limit}")
    return (w, h)
