"""Frames as the client hands them out: pixels as a numpy array, with what the server
said about them. In a notebook a frame displays itself."""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from vastray.protocol import HEADER_SIZE, FrameHeader


@dataclass
class Frame:
    image: np.ndarray  # (H, W, 3) uint8 RGB
    header: FrameHeader | None = None  # streamed frames: number, camera seq, pass, flags, times
    stats: dict[str, Any] = field(default_factory=dict)  # the server's stats of this frame
    data: bytes = b""  # the image as it came (JPEG or PNG)
    received_at: float = 0.0  # client clock (time.time()) when it arrived

    @property
    def complete(self) -> bool:
        if self.header is not None:
            return self.header.complete
        return bool(self.stats.get("complete", False))

    @property
    def final(self) -> bool:
        return self.header is not None and self.header.final

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    def to_pil(self) -> Image.Image:
        return Image.fromarray(self.image, "RGB")

    def save(self, path: str | Path) -> Path:
        """Writes the image; a .png or .jpg/.jpeg of the same format as received is
        written byte for byte, anything else re-encoded."""
        path = Path(path)
        same = (path.suffix.lower() == ".png" and self.data[:4] == b"\x89PNG") or (
            path.suffix.lower() in (".jpg", ".jpeg") and self.data[:2] == b"\xff\xd8"
        )
        if same:
            path.write_bytes(self.data)
        else:
            self.to_pil().save(path)
        return path

    def _repr_png_(self) -> bytes:
        if self.data[:4] == b"\x89PNG":
            return self.data
        out = io.BytesIO()
        self.to_pil().save(out, "PNG")
        return out.getvalue()


def decode_image(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as img:
        return np.asarray(img.convert("RGB"))


def decode_frame(message: bytes, received_at: float) -> Frame:
    header = FrameHeader.unpack(message)
    data = bytes(message[HEADER_SIZE:])
    return Frame(decode_image(data), header, {}, data, received_at)
