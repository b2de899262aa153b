"""Highlighted triangles in the renderer: pixels that see a highlighted triangle turn
towards blue, the rest of the model turns grey (ghosted) and the background stays byte
for byte what it was; without a highlight nothing changes; the same in every shading
mode, in core and out of core; the runs a set of parts becomes are checked against a
brute-force membership test."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vastray.build import BuildOptions, build_model
from vastray.camera import Camera, frame_bounds
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.parts import highlight_ranges, runs_from_ids
from vastray.render import load_model
from vastray.renderer import render_params

SOURCE = "scene:plant:20000:3"


def view(model: object, width: int = 96, height: int = 72) -> Camera:
    lo, hi = model.bounds  # type: ignore[attr-defined]
    return frame_bounds(lo, hi, width=width, height=height)


@pytest.mark.parametrize("shading", ["normal", "headlight", "sun", "ao", "indirect"])
def test_only_highlighted_triangles_change_colour(shading: str) -> None:
    model = load_model(SOURCE)
    camera = view(model)
    plain = model.render(camera, shading=shading, ao_samples=4)
    seen = np.unique(plain.prim[plain.prim >= 0])
    assert seen.size > 50
    # Every third visible triangle's id and the ones around it, as runs.
    chosen = seen[::3]
    runs = np.stack([chosen, chosen + 1], axis=1)
    runs = runs[np.r_[True, runs[1:, 0] >= runs[:-1, 1]]]
    lit = model.render(camera, shading=shading, ao_samples=4, highlight=runs)
    none = model.render(camera, shading=shading, ao_samples=4, highlight=np.zeros((0, 2), np.int64))
    np.testing.assert_array_equal(none.image, plain.image)
    np.testing.assert_array_equal(lit.prim, plain.prim)
    marked = np.isin(plain.prim, runs[:, 0])
    others = (plain.prim != -1) & ~marked
    assert marked.sum() > 20 and others.sum() > 200
    background = plain.prim == -1
    np.testing.assert_array_equal(lit.image[background], plain.image[background])
    before, after = plain.image.astype(int), lit.image.astype(int)
    # Towards blue: blue gains on red in nearly every marked pixel.
    gain = (after[..., 2] - after[..., 0]) - (before[..., 2] - before[..., 0])
    assert (gain[marked] > 0).mean() > 0.9
    spread = after.max(axis=2) - after.min(axis=2)  # 0 for a grey pixel
    if shading == "indirect":
        # Sky and bounce light are coloured, and the filter mixes neighbours: the rest
        # is far less colourful than the highlighted part, not grey.
        assert np.median(spread[others]) * 3 < np.median(spread[marked])
    else:
        assert (spread[others] <= 1).mean() > 0.99, "the rest of the model is ghosted grey"


def test_out_of_core_highlights_the_same_pixels(tmp_path: Path) -> None:
    path = tmp_path / "plant.vast"
    build_model(SOURCE, path, BuildOptions(memory=64 << 20))
    decoded = load_model(str(path))
    camera = view(decoded)
    seen = np.unique(decoded.render(camera).prim)
    seen = seen[seen >= 0]
    runs = np.array([[int(seen[len(seen) // 4]), int(seen[len(seen) // 2])]])
    params = render_params(pixels_of_error=0.0, highlight=runs)
    ref = decoded.render(camera, params)
    with OutOfCoreModel(path, make_cache(64 << 20)) as model:
        ours = model.render_complete(camera, params)
    np.testing.assert_array_equal(ours.prim, ref.prim)
    np.testing.assert_array_equal(ours.image, ref.image)
    inside = (ref.prim >= runs[0, 0]) & (ref.prim < runs[0, 1])
    assert inside.sum() > 20


def test_highlight_ranges_match_brute_force() -> None:
    rng = np.random.default_rng(7)
    n = 5000
    part_of = np.repeat(rng.integers(0, 9, 300), rng.integers(1, 40, 300))[:n]
    n = len(part_of)
    ids = rng.permutation(n)  # a mesh holds its triangles in any order
    firsts, parts = runs_from_ids(ids, part_of[ids])
    assert firsts[0] == 0 and np.all(np.diff(firsts.astype(np.int64)) > 0)
    assert np.all(parts[1:] != parts[:-1])
    for selected in ([3], [0, 5, 8], [], list(range(9))):
        ranges = highlight_ranges(firsts, parts, n, selected)
        member = np.zeros(n, bool)
        for lo, hi in ranges:
            member[lo:hi] = True
        np.testing.assert_array_equal(member, np.isin(part_of, selected))
        if len(ranges) > 1:
            assert np.all(ranges[1:, 0] > ranges[:-1, 1]), "adjacent runs are merged"


@pytest.mark.parametrize(
    ("ranges", "message"),
    [
        ([[5, 5]], "must not be empty"),
        ([[4, 9], [8, 12]], "sorted and disjoint"),
        ([[-1, 3]], r"\[0, 2\^32\)"),
    ],
)
def test_bad_highlights_are_refused(ranges: list[list[int]], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        render_params(highlight=np.array(ranges))
