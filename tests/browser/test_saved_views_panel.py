"""The Views panel in a real Chromium: a view saved with the model (camera, section
planes) is listed, a click on it brings them back after the user moved on, and "×"
deletes it; a page of the same model opened with a viewing token sees the list change
as views are saved and deleted, and has no way to save or delete one."""

from __future__ import annotations

from typing import Any

import numpy as np


def test_a_view_saved_with_the_model_comes_back(
    open_viewer: Any, server: Any, api: Any, model: dict[str, Any]
) -> None:
    for old in api.get(f"/api/models/{model['id']}/views").json()["views"]:
        api.delete(f"/api/models/{model['id']}/views/{old['id']}").raise_for_status()
    v = open_viewer(server.open_url)
    n = v.wait_final()
    page = v.page
    # A page of the same model opened with a viewing token, open all along: it hears of
    # the views saved and deleted (the stream's model_views event) and cannot save one.
    token = api.post(f"/api/models/{model['id']}/tokens", json={"ttl_seconds": 600}).json()["token"]
    guest = open_viewer(f"{server.url}/?token={token}&model={model['id']}", role="guest")
    guest.wait_final()
    guest.page.locator("#views-panel summary").click()
    guest.wait_for("() => document.getElementById('model-views').innerText.includes('no views saved')")
    assert not guest.page.locator("#model-view-save").is_visible()
    page.locator("#views-panel summary").click()
    v.wait_for("() => document.getElementById('model-views').innerText.includes('no views saved')")

    page.locator("#sections-panel summary").click()
    page.get_by_role("button", name="add a section plane across X").click()
    n = v.wait_final(n)
    saved_camera = v.js("() => ({...window.vastray.camera})")
    page.locator("#model-view-name").fill("cut across x")
    page.locator("#model-view-save").click()
    v.wait_for("() => document.getElementById('model-views').innerText.includes('cut across x')")
    (saved,) = api.get(f"/api/models/{model['id']}/views").json()["views"]
    assert saved["name"] == "cut across x" and len(saved["sections"]) == 1
    np.testing.assert_allclose(saved["camera"]["eye"], saved_camera["eye"])

    # Move on: another camera, no planes; then the saved view brings both back.
    v.drag(150, 40)
    page.locator("#section-clear").click()
    n = v.wait_final(n, v.js("window.vastray.seq"))
    assert v.js("window.vastray.panels.sections.length") == 0
    page.locator("#model-views li", has_text="cut across x").click()
    n = v.wait_final(n, v.js("window.vastray.seq"))
    shown = v.shown()["camera"]
    np.testing.assert_allclose(shown["eye"], saved_camera["eye"], rtol=1e-12)
    np.testing.assert_allclose(shown["target"], saved_camera["target"], rtol=1e-12)
    sent = [m for m in v.sent if m["type"] == "sections"][-1]["planes"]
    plane = lambda p: (p["normal"], p["offset"])  # noqa: E731
    assert [plane(p) for p in sent] == [plane(p) for p in saved["sections"]]
    v.shot("back-at-the-saved-view")

    # The guest's list got it as it was saved, without a way to delete it.
    guest.wait_for("() => document.getElementById('model-views').innerText.includes('cut across x')")
    assert guest.page.locator("#model-views button").count() == 0

    page.get_by_role("button", name="delete the view cut across x").click()
    v.wait_for("() => document.getElementById('model-views').innerText.includes('no views saved')")
    guest.wait_for("() => document.getElementById('model-views').innerText.includes('no views saved')")
    assert api.get(f"/api/models/{model['id']}/views").json()["views"] == []
    assert not v.errors_received() and not guest.errors_received()
