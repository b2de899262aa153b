"""Parts through the server, as the page and the Python client use them: an OBJ with
named objects is uploaded and built; the model lists its parts (names, triangle counts,
bounds as the OBJ has them) and searches them by name; a pick names the part it hits;
a streamed view highlights a part, and only that part's pixels change."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import numpy as np
import pytest
from assembly import BOXES, CELLS, build_assembly
from serverproc import ServerProcess

from vastray.client import Client


@pytest.fixture(scope="module")
def model(api: httpx.Client, tmp_path_factory: pytest.TempPathFactory) -> dict:
    return build_assembly(api, tmp_path_factory.mktemp("obj"))


@pytest.fixture(scope="module")
def client(server: ServerProcess) -> Iterator[Client]:
    with Client(server.url, key=server.key) as c:
        yield c


def test_the_model_lists_its_parts_as_the_obj_has_them(api: httpx.Client, model: dict) -> None:
    assert model["part_ids"] is True and model["part_count"] == len(BOXES)
    found = api.get(f"/api/models/{model['id']}/parts").json()
    assert found["total"] == len(BOXES)
    by_name = {p["name"]: p for p in found["parts"]}
    assert set(by_name) == {name for name, _, _ in BOXES}
    for name, lo, side in BOXES:
        part = by_name[name]
        assert part["triangles"] == 12 * CELLS * CELLS
        np.testing.assert_allclose(part["bounds"][0], lo, atol=1e-9)
        np.testing.assert_allclose(part["bounds"][1], np.array(lo) + side, atol=1e-9)
    pumps = api.get(f"/api/models/{model['id']}/parts", params={"q": "PUMP"}).json()
    assert sorted(p["name"] for p in pumps["parts"]) == ["pump housing", "pump impeller"]
    assert api.get(f"/api/models/{model['id']}/parts", params={"q": "nothing"}).json() == {
        "total": 0,
        "parts": [],
    }


def test_parts_are_found_by_id(api: httpx.Client, client: Client, model: dict) -> None:
    """`ids` gives exactly the parts asked for (what a page needs to box highlighted parts
    it was not sent), with a name search too; unknown ids are left out, and a list that
    is not one of ids is refused with the parameter named."""
    url = f"/api/models/{model['id']}/parts"
    every = {p["id"]: p for p in api.get(url).json()["parts"]}
    some = sorted(every)[1::2]
    found = api.get(url, params={"ids": ",".join(map(str, [*some, 10_000]))}).json()
    assert found["total"] == len(some) and [p["id"] for p in found["parts"]] == some
    assert found["parts"] == [every[i] for i in some]
    pumps = [i for i in every if every[i]["name"].startswith("pump")]
    both = api.get(url, params={"q": "pump", "ids": ",".join(map(str, every))}).json()
    assert sorted(p["id"] for p in both["parts"]) == sorted(pumps)
    assert [p.id for p in client.parts(model["id"], ids=reversed(some))] == some
    assert client.parts(model["id"], ids=[]) == []
    for bad in ("1,,2", ",5", "5,", "-1", "a", "1;2"):
        r = api.get(url, params={"ids": bad})
        message = r.json()["error"]["message"]
        assert r.status_code == 422 and message.startswith("ids: part ids are whole numbers"), (bad, r.text)
    assert api.get(url, params={"ids": f" {some[0]}, 10000"}).json()["parts"] == [every[some[0]]]
    # Without a credential, a bad list is still a 401: who asks comes first.
    assert httpx.get(f"{api.base_url}{url}", params={"ids": ",5"}).status_code == 401


def test_a_pick_names_the_part_it_hits(client: Client, model: dict) -> None:
    parts = {p.name: p.id for p in client.parts(model["id"])}
    rays = [((lo[0] + side / 2, 0.5, 5.0), (0.0, 0.0, -1.0)) for _, lo, side in BOXES]
    rays.append(((1.5, 0.5, 5.0), (0.0, 0.0, -1.0)))  # between two boxes
    hits = client.pick(model["id"], rays=rays)
    for (name, _, _), hit in zip(BOXES, hits[:-1], strict=True):
        assert hit.hit and hit.part == name and hit.part_id == parts[name]
        assert hit.distance == pytest.approx(4.0, abs=1e-5)
    assert not hits[-1].hit and hits[-1].part is None


def test_a_highlighted_part_changes_only_its_own_pixels(client: Client, model: dict) -> None:
    valve = next(p for p in client.parts(model["id"], "valve"))
    camera = {"eye": [2.5, 0.5, 9.0], "target": [2.5, 0.5, 0.5], "up": [0, 1, 0], "fov": 40}
    with client.view(model["id"], viewport=(240, 120), camera=camera) as view:
        view.final()
        before = view.screenshot().image.astype(int)
        view.set_highlight([valve.id])
        after = view.screenshot().image.astype(int)
    blue_before = (before[..., 2] - before[..., 0]) > 40
    blue = (after[..., 2] - after[..., 0]) > 40
    assert blue.sum() > 100 and not blue_before.any(), "the highlighted part turns blue"
    # The valve is the right-hand box (x in [4, 5]; the camera looks at x = 2.5).
    columns = np.flatnonzero(blue.any(axis=0))
    assert columns.min() > 240 * 0.6, "pixels of other parts turned blue"
    spread = after.max(axis=2) - after.min(axis=2)
    left = (before.sum(axis=2) != after.sum(axis=2)) & (np.arange(240) < 240 * 0.5)
    assert (spread[left] <= 1).mean() > 0.8, "the other parts are ghosted grey (edges blend with the sky)"
