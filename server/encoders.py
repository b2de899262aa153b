"""Image encoders: JPEG through Pillow's libjpeg-turbo for streamed frames and quick
renders, PNG for lossless screenshots. Encoding is CPU work: callers run it off the
event loop (in the render executor)."""

from __future__ import annotations

import io
from typing import Literal

import numpy as np
from PIL import Image

ImageFormat = Literal["png", "jpeg"]
MEDIA_TYPES: dict[str, str] = {"png": "image/png", "jpeg": "image/jpeg"}


def encode(image: np.ndarray, fmt: ImageFormat, *, quality: int = 90) -> bytes:
    """(H, W, 3) uint8 RGB to the bytes of a PNG or baseline JPEG."""
    pil = Image.fromarray(np.ascontiguousarray(image), "RGB")
    out = io.BytesIO()
    if fmt == "jpeg":
        # 4:2:0 chroma subsampling, as video does: rendered frames are smooth shading.
        pil.save(out, "JPEG", quality=quality, subsampling=2, optimize=False)
    else:
        # Level 1: screenshots are few and large; most of zlib's time goes to the last
        # few percent of size.
        pil.save(out, "PNG", compress_level=1)
    return out.getvalue()
