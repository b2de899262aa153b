"""The native LZ4 block decoder (liblz4's safe decoder behind native.lz4_decompress and
the block reads) against the `lz4` package: round trips on varied data, and fuzzed
corrupt blocks that must give an error, never a crash, and the package's answer
whichever way it goes."""

from __future__ import annotations

import lz4.block
import numpy as np
import pytest

from vastray import native


def sample_blocks(rng: np.random.Generator) -> list[bytes]:
    floats = rng.normal(size=4096).astype("<f4").tobytes()  # hardly compressible
    grid = np.repeat(np.arange(64, dtype="<u4"), 256).tobytes()  # long runs
    text = b"vastray renders massive models; " * 2000
    nodes = np.tile(np.array([3, 7, 11, 0x40490FDB], dtype="<u4"), 4096).tobytes()  # 8-byte-node-like
    return [
        b"",
        b"x",
        bytes(65536),
        rng.integers(0, 256, 65536, dtype=np.uint8).tobytes(),
        floats,
        grid,
        text[:65536],
        nodes[:65536],
        rng.integers(0, 4, 5000, dtype=np.uint8).tobytes(),  # small alphabet: many short matches
    ]


@pytest.mark.parametrize("mode", ["default", "high_compression"])
def test_round_trip_matches_the_library(mode: str) -> None:
    for raw in sample_blocks(np.random.default_rng(1)):
        packed = lz4.block.compress(raw, mode=mode, store_size=False)
        assert native.lz4_decompress(packed, len(raw)) == raw


def test_wrong_expected_size_is_an_error() -> None:
    raw = b"abcdefgh" * 1000
    packed = lz4.block.compress(raw, store_size=False)
    for size in (len(raw) - 1, len(raw) + 1, 0):
        with pytest.raises(ValueError, match="corrupt LZ4 block"):
            native.lz4_decompress(packed, size)


def test_fuzzed_blocks_never_crash_and_agree_with_the_library() -> None:
    rng = np.random.default_rng(7)
    blocks = [b for b in sample_blocks(rng) if b]
    accepted = rejected = 0
    for case in range(4000):
        raw = blocks[case % len(blocks)]
        packed = bytearray(lz4.block.compress(raw, store_size=False))
        kind = case % 3
        if kind == 0:  # flip random bits
            for _ in range(int(rng.integers(1, 4))):
                i = int(rng.integers(0, len(packed)))
                packed[i] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1:  # truncate
            packed = packed[: int(rng.integers(0, len(packed)))]
        else:  # overwrite a random span with random bytes
            i = int(rng.integers(0, len(packed)))
            span = rng.integers(0, 256, min(8, len(packed) - i), dtype=np.uint8).tobytes()
            packed[i : i + len(span)] = span
        data = bytes(packed)
        error = ""
        try:
            ours: bytes | None = native.lz4_decompress(data, len(raw))
        except ValueError as exc:
            ours, error = None, str(exc)
        try:
            theirs: bytes | None = lz4.block.decompress(data, uncompressed_size=len(raw))
        except lz4.block.LZ4BlockError:
            theirs = None
        if theirs is not None and len(theirs) == len(raw):
            assert ours == theirs, f"case {case}: the package decodes this block differently ({error})"
        else:
            assert ours is None, f"case {case}: accepted a block the package rejects"
            assert error.startswith("corrupt LZ4 block: "), error
        if ours is None:
            rejected += 1
        else:
            assert len(ours) == len(raw)
            accepted += 1
    # Both outcomes were exercised.
    assert rejected > 100 and accepted > 100
