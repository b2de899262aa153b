"""Frame encoders side by side: Pillow's JPEG (libjpeg-turbo inside Pillow's wheel)
against simplejpeg (a thin wrapper of libjpeg-turbo), and PNG at the levels a
screenshot might use, on rendered frames of the demo at the stream's sizes.

    python bench/encode.py [--repeats 30]

Results go to bench/results/encode.md. simplejpeg is optional (`pip install
simplejpeg`); without it only Pillow is measured.
"""

from __future__ import annotations

import argparse
import io
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS_DIR, machine_info, markdown_table

from vastray.camera import frame_bounds
from vastray.render import load_model

SIZES = ((320, 180), (640, 360), (1280, 720), (1920, 1080))


def pillow_jpeg(image: np.ndarray, quality: int) -> bytes:
    out = io.BytesIO()
    Image.fromarray(image).save(out, "JPEG", quality=quality, subsampling=2)
    return out.getvalue()


def pillow_png(image: np.ndarray, level: int) -> bytes:
    out = io.BytesIO()
    Image.fromarray(image).save(out, "PNG", compress_level=level)
    return out.getvalue()


def best_ms(fn: object, repeats: int) -> tuple[float, int]:
    times, size = [], 0
    for _ in range(repeats):
        t = time.perf_counter()
        data = fn()  # type: ignore[operator]
        times.append(1000 * (time.perf_counter() - t))
        size = len(data)
    return statistics.median(times), size


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--out", default=str(RESULTS_DIR / "encode.md"))
    args = ap.parse_args()
    try:
        import simplejpeg
    except ImportError:
        simplejpeg = None
    model = load_model("demo")
    rows = []
    for w, h in SIZES:
        image = model.render(frame_bounds(*model.bounds, width=w, height=h), shading="sun").image
        cases = {
            "Pillow JPEG q80": lambda im=image: pillow_jpeg(im, 80),
            "Pillow PNG level 1": lambda im=image: pillow_png(im, 1),
            "Pillow PNG level 6": lambda im=image: pillow_png(im, 6),
        }
        if simplejpeg is not None:
            cases["simplejpeg q80"] = lambda im=image: simplejpeg.encode_jpeg(
                np.ascontiguousarray(im), quality=80, colorspace="RGB", colorsubsampling="420"
            )
        results = {name: best_ms(fn, args.repeats) for name, fn in cases.items()}
        base = results["Pillow JPEG q80"][0]
        for name, (ms, size) in results.items():
            rows.append([f"{w}x{h}", name, f"{ms:.2f}", f"{size / 1024:.0f}", f"{base / ms:.2f}x"])
    text = "\n".join(
        [
            "# Frame encoders",
            "",
            f"`python bench/encode.py` — a sun-lit frame of the demo at each size, "
            f"median of {args.repeats} encodes, "
            "one thread. Speed relative to Pillow's JPEG (higher: faster).",
            "",
            *(f"- {k}: {v}" for k, v in machine_info().items()),
            "",
            markdown_table(["size", "encoder", "ms", "KiB", "speed vs Pillow JPEG"], rows),
        ]
    )
    Path(args.out).write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
