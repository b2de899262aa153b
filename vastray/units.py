"""Sizes as people type them: '2G', '512M', '1.5GiB', or a plain byte count."""

from __future__ import annotations

_SCALE = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


def parse_bytes(text: str | int, what: str = "size") -> int:
    """Bytes in `text` ('2G', '512M', '1.5GiB', '4096'); `what` names the setting in the
    error message."""
    if isinstance(text, int):
        if text <= 0:
            raise ValueError(f"{what} must be positive, got {text}")
        return text
    s = text.strip().upper().removesuffix("B").removesuffix("I")
    scale = _SCALE.get(s[-1:], 1)
    number = s[:-1] if scale != 1 else s
    try:
        value = float(number)
    except ValueError:
        raise ValueError(f"{what} {text!r} is not a size like 2G or 512M") from None
    if not value > 0 or value != value or value == float("inf"):
        raise ValueError(f"{what} must be positive, got {text!r}")
    return int(value * scale)


def format_bytes(n: float) -> str:
    """1536 -> '1.5 KiB'; for messages and logs."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"
