"""Frames of native targets from the camera-and-parameter keywords the tests spell views
in: `render_view(scene, eye, target, up, fov, width, height, shading=..., sun=...)`,
positional or by name, for a native.Scene or a native.CachedModel. `sun` is short for
sun_direction. Returns a vastray.renderer.Frame."""

from __future__ import annotations

from typing import Any

from vastray import native
from vastray.camera import Camera
from vastray.renderer import Frame, trace

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
