"""Image encoders: JPEG through simplejpeg, a thin wrapper of libjpeg-turbo, for
streamed frames and quick renders (1.4x Pillow's JPEG at 720p and 1080p for the same
bytes: bench/results/encode.md); PNG through Pillow for lossless screenshots. Encoding
is CPU work: callers run it off the event loop (in the render executor)."""

from __future__ import annotations

import io
from typing import Literal

import numpy as np
import simplejpeg
from PIL import Image

ImageFormat = Literal["png", "jpeg"]
MEDIA_TYPES: dict[str, str] = {"png": "image/png", "jpeg": "image/jpeg"}


def encode(image: np.ndarray, fmt: ImageFormat, *, quality: int = 90) -> bytes:
    """(H, W, 3) uint8 RGB to the bytes of a PNG or baseline JPEG."""
    pixels = np.ascontiguousarray(image)
    if fmt == "jpeg":
        # 4:2:0 chroma subsampling, as video does: rendered frames are smooth shading.
        return bytes(
            simplejpeg.encode_jpeg(pixels, quality=quality, colorspace="RGB", colorsubsampling="420")
        )
    # PNG level 1: screenshots are few and large; level 6 takes 1.6x as long for 15 %
    # fewer bytes (bench/results/encode.md).
    out = io.BytesIO()
    Image.fromarray(pixels, "RGB").save(out, "PNG", compress_level=1)
    return out.getvalue()
