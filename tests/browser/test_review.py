"""A design review in two browser contexts: the presenter starts it from the page (from
the view it shows), a follower opens the join link; the follower sees the presenter's
camera, pointer and annotation, can look around on its own and go back to following."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from conftest import grid, pick


def a_hit(api: Any, model_id: str, viewer: Any) -> tuple[tuple[float, float], dict[str, Any]]:
    """An image point of the frame shown that hits the model near the middle of the view."""
    shown = viewer.shown()
    points = grid(shown, 7, 5, margin=0.3)
    hits = pick(api, model_id, shown, points)
    return next((p, h) for p, h in zip(points, hits, strict=True) if h["hit"])


@pytest.mark.slow
def test_a_follower_sees_the_presenters_camera_pointer_and_annotation(
    open_viewer: Any, server: Any, api: Any, model: dict[str, Any]
) -> None:
    # The presenter starts a review from the page, from where it has looked around to.
    presenter = open_viewer(server.open_url, "presenter")
    presenter.wait_final()
    p = presenter.page
    presenter.drag(-90, 20)
    presenter.wait_final(seq=presenter.js("window.vastray.seq"))
    n = presenter.frames()
    p.select_option("#shading", "normal")
    presenter.wait_final(n)
    eye, target = presenter.js("[window.vastray.camera.eye, window.vastray.camera.target]")
    p.locator("#review-panel summary").click()
    p.get_by_role("button", name="Start a review").click()
    p.wait_for_url("**/?review=*")
    presenter.wait_final()
    review_id = presenter.js("window.vastray.reviewId")
    assert p.locator("#review-role").inner_text().startswith("You present")
    # The page reloaded into the review, and the shared view starts where it looked.
    assert presenter.js("window.vastray.camera.eye") == pytest.approx(eye)
    assert presenter.js("window.vastray.camera.target") == pytest.approx(target)
    assert presenter.shown()["camera"]["eye"] == pytest.approx(eye)
    assert p.locator("#shading").input_value() == "normal"
    join = p.locator("#review-link").input_value()
    # The link to share is the follower's, never the presenter's own.
    assert f"review={review_id}" in join and "token=vt_" in join
    assert join.split("token=")[1] not in p.url

    follower = open_viewer(join, "follower")
    f = follower.page
    follower.wait_final()
    follower.shot("joined")
    # The follower sees the model (named, though a review link lists no models) and who is there.
    assert "plant" in f.locator("#model-select option:checked").inner_text()
    assert f.locator("#upload-button").is_hidden()
    for page in (p, f):
        page.wait_for_function("document.querySelectorAll('#participants li').length === 2")
    assert "(you)" in f.locator("#participants li", has_text="following").inner_text()
    # Following, it cannot change what the presenter shows.
    assert f.locator("#shading").is_disabled() and f.locator("#poe").is_disabled()

    # The presenter's camera: the follower's frames follow it.
    before = follower.thumbnail()
    n = follower.frames()
    presenter.drag(150, 30)
    seq = presenter.js("window.vastray.seq")
    presenter.wait_final(seq=seq)
    follower.wait_final(n, seq)
    follower.shot("followed")
    assert follower.shown()["camera"]["eye"] == pytest.approx(presenter.js("window.vastray.camera.eye"))
    assert np.abs(follower.thumbnail() - before).mean() > 8, "the follower's picture did not move"
    # The very same picture (both windows are the same size).
    assert np.abs(follower.thumbnail() - presenter.thumbnail()).mean() < 4

    # The presenter's pointer: a click in pointer mode shows on the follower's image.
    p.locator("#pointer-mode").check()
    point, hit = a_hit(api, model["id"], presenter)
    presenter.click_image(*point)
    follower.wait_for("() => document.querySelectorAll('#overlay path.pointer').length === 1")
    follower.shot("pointer")
    label = f.locator("#overlay text.pointer-label").text_content()
    assert label == presenter.js("window.vastray.panels.review.name")
    pointers = follower.js("[...window.vastray.panels.pointers.values()].map((x) => x.position)")
    assert pointers == [pytest.approx(hit["position"], abs=1e-6 * np.ptp(model["bounds"]))]
    # Where the follower draws it: where that point is on its image.
    d = f.locator("#overlay path.pointer").get_attribute("d").split()  # "M<x> <y> l …"
    x, y = float(d[0][1:]), float(d[1])
    expected = follower.page_point(*point)
    box = f.locator("#view").bounding_box()
    assert (x + box["x"], y + box["y"]) == pytest.approx(expected, abs=2.0)

    # An annotation: pick a point, write a note, Add; the follower's list and image show it.
    p.locator("#pointer-mode").uncheck()
    presenter.click_image(*point)
    presenter.wait_for("() => document.getElementById('pick').innerText.startsWith('point:')")
    p.locator("#annotation-text").fill("check this flange")
    p.get_by_role("button", name="Add").click()
    follower.wait_for("() => document.getElementById('annotations').innerText.includes('check this flange')")
    f.wait_for_function(
        "[...document.querySelectorAll('#overlay text.note-label')]"
        ".some((t) => t.textContent === 'check this flange')"
    )
    follower.shot("annotation")
    notes = api.get(f"/api/reviews/{review_id}").json()["annotations"]
    assert [n["text"] for n in notes] == ["check this flange"]
    assert notes[0]["position"] == pytest.approx(hit["position"], abs=1e-6 * np.ptp(model["bounds"]))

    # The follower looks around on its own (the presenter's view stays), then follows again.
    presenter_eye = presenter.js("window.vastray.camera.eye")
    n = follower.frames()
    follower.drag(-140, 0)
    assert not f.locator("#follow").is_checked()
    follower.wait_final(n, follower.js("window.vastray.seq"))
    assert follower.shown()["camera"]["eye"] != pytest.approx(presenter_eye)
    assert presenter.js("window.vastray.camera.eye") == presenter_eye
    n = follower.frames()
    f.locator("#follow").check()
    follower.wait_final(n)
    assert follower.shown()["camera"]["eye"] == pytest.approx(presenter_eye)
    # A standard view is navigation too: the follower goes free to look from the top
    # (sending its camera while still following would be refused: errors_received below).
    n = follower.frames()
    f.locator("#standard-views button[data-view=top]").click()
    assert not f.locator("#follow").is_checked()
    follower.wait_final(n, follower.js("window.vastray.seq"))
    assert presenter.js("window.vastray.camera.eye") == presenter_eye
    n = follower.frames()
    f.locator("#follow").check()
    follower.wait_final(n)

    # The presenter hands the role over, explicitly; the new presenter drives the shared view.
    p.get_by_role("button", name="hand the presenter role to").click()
    follower.wait_for("() => window.vastray.role === 'presenter'")
    presenter.wait_for("() => window.vastray.role === 'follower' && window.vastray.following")
    assert f.locator("#review-role").inner_text().startswith("You present")
    assert p.locator("#shading").is_disabled() and not f.locator("#shading").is_disabled()
    n = presenter.frames()
    follower.drag(0, 60)
    seq = follower.js("window.vastray.seq")
    presenter.wait_final(n, seq)
    assert presenter.shown()["camera"]["eye"] == pytest.approx(follower.js("window.vastray.camera.eye"))
    presenter.shot("handed-over")
    for v in (presenter, follower):
        assert not v.errors_received(), v.errors_received()
