"""Frames of native targets from the camera-and-parameter keywords the tests spell views
in: `render_view(scene, eye, target, up, fov, width, height, shading=..., sun=...)`,
positional or by name, for a native.Scene or a native.CachedModel. `sun` is short for
sun_direction. Returns a vastray.renderer.Frame. `model_views(path)`: two cameras that
frame a built model from two sides, the views the layout tests compare frames in.
`DIGEST_SCRIPT`: the head of the scripts that tests run in other processes (another ISA
path, an emulated CPU) to compare answers by digest."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from vastray import native
from vastray.camera import Camera, frame_bounds
from vastray.modelfile import ModelFile
from vastray.renderer import Frame, trace

DIGEST_SCRIPT = r"""
import hashlib, json, sys
import numpy as np
from vastray import native
from vastray.build import build_model
from vastray.camera import Camera, frame_bounds
from vastray.modelfile import ModelFile
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.renderer import trace

def digest(*arrays):
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]

# Digests of every shading mode's frame, in core and out of core at PoE 0 and 2, for each
# named camera and packet size.
def frame_digests(scene, model, cameras, packet_sizes, ao_samples):
    out = {}
    for view, cam in cameras.items():
        for shading in ("normal", "headlight", "sun", "ao", "indirect"):
            for packets in packet_sizes:
                kw = dict(shading=shading, packets=packets, ao_samples=ao_samples)
                f = trace(scene, cam.to_native(), **kw)
                out[f"in-core {view} {shading} {packets}"] = digest(f.image, f.depth, f.prim)
                for poe in (0.0, 2.0):
                    f = model.render_complete(cam, pixels_of_error=poe, **kw)
                    key = f"out-of-core {view} {shading} {packets} PoE {poe:g}"
                    out[key] = digest(f.image, f.depth, f.prim)
    return out
"""

CAMERA_FIELDS = ("eye", "target", "up", "fov", "width", "height")


def split_view(*args: Any, **kwargs: Any) -> tuple[native.Camera, dict[str, Any]]:
    camera = dict(zip(CAMERA_FIELDS, args, strict=False))
    for name in CAMERA_FIELDS:
        if name in kwargs:
            camera[name] = kwargs.pop(name)
    if "sun" in kwargs:
        kwargs["sun_direction"] = kwargs.pop("sun")
    return native.Camera(**camera), kwargs


def render_view(model: native.Scene | native.CachedModel, /, *args: Any, **kwargs: Any) -> Frame:
    camera, params = split_view(*args, **kwargs)
    return trace(model, camera, **params)


def render_camera(model: native.Scene | native.CachedModel, camera: Camera, **params: Any) -> Frame:
    return trace(model, camera, **params)


def model_views(path: Path, size: tuple[int, int] = (96, 72)) -> list[Camera]:
    with ModelFile(path) as model:
        lo, hi = model.bounds
    directions = ((0.5, 0.4, 0.8), (-0.7, 0.9, -0.3))
    return [frame_bounds(lo, hi, width=size[0], height=size[1], direction=d) for d in directions]
