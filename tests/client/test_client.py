"""The Python client end to end against a real server, blocking and asyncio: upload a
mesh and build it with progress, render, pick, stream a view (frames as numpy arrays
with their headers, a moved camera, the final frame, a lossless screenshot, picks over
the stream), errors as exceptions, and a view that survives a server restart."""

from __future__ import annotations

import asyncio
import socket
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image
from serverproc import ServerProcess

from vastray import scenes
from vastray.client import AsyncClient, BuildFailedError, Client, VastrayError
from vastray.schemas import JobInfo, section_box


@pytest.fixture(scope="module")
def mesh(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("mesh") / "pump.ply"
    scenes.write_scene("plant", 30_000, 21, path)
    return path


def orbit_eye(bounds: tuple, angle: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    lo, hi = (np.asarray(b) for b in bounds)
    centre, size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    eye = centre + size * np.array([np.cos(angle), 0.6, np.sin(angle)])
    return tuple(eye.tolist()), tuple(centre.tolist())


def test_blocking_client_end_to_end(url: str, mesh: Path, tmp_path: Path) -> None:
    with Client(url) as vr:
        assert vr.health()["status"] == "ready"
        up = vr.upload(mesh, name="pump", up=(0, 0, 2))  # a z-up mesh, said so at once
        assert up.kind == "mesh" and up.bytes == mesh.stat().st_size and up.created is not None
        seen: list[JobInfo] = []
        job = vr.wait(up.created.job, progress=seen.append)
        assert job.state == "succeeded" and seen[-1].percent == 100.0 and len(seen) >= 2
        model = vr.model(job.model_id)
        assert model.state == "ready" and model.name == "pump" and model.triangles > 25_000
        assert model.up == (0.0, 0.0, 1.0)
        assert model.id in {m.id for m in vr.models()}

        still = vr.render(model, camera={"width": 200, "height": 150}, quality={"shading": "sun"})
        assert still.image.shape == (150, 200, 3) and still.complete and still.stats["frames"] >= 1
        assert still._repr_png_()[:4] == b"\x89PNG"  # displays in a notebook
        png = still.save(tmp_path / "still.png")
        assert np.array_equal(np.asarray(Image.open(png).convert("RGB")), still.image)

        hits = vr.pick(model, points=[(100, 75), (0.5, 0.5)], camera={"width": 200, "height": 150})
        assert hits[0].hit and hits[0].triangle is not None and not hits[1].hit

        with vr.view(model, viewport=(240, 160)) as view:
            assert view.model_info["id"] == model.id
            first = view.final()
            assert first.final and first.complete and first.image.shape == (160, 240, 3)
            assert first.header is not None and first.header.camera_seq == 0
            assert first.stats["frame"] == first.header.frame and first.stats["working_set_bytes"] > 0
            eye, target = orbit_eye(model.bounds, 2.2)
            seq = view.set_camera(eye, target)
            moved = view.final()
            assert moved.header.camera_seq == seq
            assert np.abs(moved.image.astype(int) - first.image.astype(int)).mean() > 3
            shot = view.screenshot()
            assert shot.header.format_name == "png" and shot.data[:4] == b"\x89PNG"
            assert shot.image.shape == moved.image.shape
            # The same view as the last JPEG frame, without its compression error.
            mse = ((shot.image.astype(float) - moved.image.astype(float)) ** 2).mean()
            assert 10 * np.log10(255**2 / max(mse, 1e-9)) > 28
            picked = view.pick([(120, 80)])
            assert picked[0].hit and picked[0].distance > 0
            view.set_quality(shading="normal", aa_passes=1)
            normal = view.final()
            assert normal.header.pass_number == 1
            # A design review started from this view starts there.
            started = vr.start_review(
                model, title="pump check", camera=view.camera, quality={"shading": "normal"}
            )
            rid = started["review"]["id"]
            assert f"review={rid}" in started["join_url"] and started["join_token"] in started["join_url"]
            review = vr.review(rid)
            assert review["title"] == "pump check" and review["participants"] == []
            assert review["view"]["camera"]["eye"] == pytest.approx(eye)
            assert review["view"]["quality"]["shading"] == "normal"
            with pytest.raises(VastrayError) as err:
                vr.start_review(model, camera={"eye": eye, "target": eye})
            assert err.value.status == 422 and err.value.code == "invalid_camera"

        # Said to be x-up after all (and renamed): a new view starts upright about +x.
        turned = vr.update_model(model, name="pump (x-up)", up=(3, 0, 0))
        assert turned.up == (1.0, 0.0, 0.0) and vr.model(model).name == "pump (x-up)"
        with vr.view(model, viewport=(240, 160)) as view:
            assert view.camera.up == (1.0, 0.0, 0.0) and view.model_info["up"] == [1.0, 0.0, 0.0]
        with pytest.raises(VastrayError) as err:
            vr.update_model(model, up=(0, 0, 0))
        assert err.value.status == 422 and "zero length" in str(err.value)

        with pytest.raises(VastrayError) as err:
            vr.render("mdl-nosuch")
        assert err.value.status == 404 and err.value.code == "model_not_found"
        bad = vr.upload(_broken(tmp_path), name="broken")
        with pytest.raises(BuildFailedError) as failed:
            vr.wait(bad.created.job)
        assert failed.value.job.state == "failed" and "broken.ply" in failed.value.job.error
        assert vr.delete(model) in (True, False)


def _broken(tmp_path: Path) -> Path:
    path = tmp_path / "broken.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nend_header\n\x00")
    return path


def test_async_client_end_to_end(url: str) -> None:
    async def go() -> None:
        async with AsyncClient(url) as vr:
            job = await vr.build("scene:spheres:8000:4", name="spheres")
            job = await vr.wait(job)
            frame = await vr.render(job.model_id, camera={"width": 64, "height": 48}, format="jpeg")
            assert frame.image.shape == (48, 64, 3) and frame.data[:2] == b"\xff\xd8"
            async with vr.view(job.model_id, viewport=(128, 96)) as view:
                final = await view.final()
                assert final.final and final.image.shape == (96, 128, 3)
                eye, target = orbit_eye(tuple(view.model_info["bounds"]), 1.0)
                frames = []
                for i in range(8):
                    await view.set_camera(eye, target, fov=45 + i)
                    frames.append(await view.next_frame(30))
                assert any(f.header.moving for f in frames)
                last = await view.final()
                assert last.header.camera_seq == 8
                hits = await view.pick([(64, 48)])
                assert hits[0].hit
            token = await vr.token(job.model_id, ttl=60)
            async with AsyncClient(url.split("?")[0], key=token) as viewer:
                assert [m.id for m in await viewer.models()] == [job.model_id]
                with pytest.raises(VastrayError) as err:
                    await viewer.build("demo")
                assert err.value.status == 403

    asyncio.run(go())


def test_scripts_present_and_follow_a_review(url: str) -> None:
    """Two scripts in one review, each from its link: the presenter moves, the follower
    gets frames of the presenter's camera and knows where it is; a follower cannot move
    until it stops following; notes and the participant list reach both, and the
    review says where its shared view is."""
    with Client(url) as admin:
        job = admin.wait(admin.build("scene:spheres:5000:3", up=(0, 0, 1)))
        started = admin.start_review(job.model_id, title="scripted")
    with (
        Client(started["presenter_url"]) as pat,
        Client(started["join_url"]) as fay,
        pat.join(name="pat", viewport=(160, 100)) as lead,
        fay.join(name="fay", viewport=(120, 90)) as follower,
    ):
        assert (lead.role, follower.role) == ("presenter", "follower") and follower.following
        assert lead.camera.up == follower.camera.up == (0.0, 0.0, 1.0)  # the model's up
        eye, target = orbit_eye(tuple(lead.model_info["bounds"]), 1.3)
        seq = lead.set_camera(eye, target)
        shown = lead.final(seq)
        # The follower's frames are the presenter's (the same pixels, its aspect).
        got = follower.final(seq)
        assert got.header.camera_seq == seq and got.image.shape == shown.image.shape == (100, 160, 3)
        assert np.array_equal(got.image, shown.image)
        assert follower.camera.eye == pytest.approx(eye)
        with pytest.raises(VastrayError) as err:  # (looking back) not while following
            follower.set_camera(target, eye)
        assert err.value.code == "following" and follower.camera.eye == pytest.approx(eye)
        assert str(err.value).endswith("follow(False) first (following)")
        # On its own, it moves where it likes; the presenter's view stays put.
        follower.follow(False)
        own = follower.set_camera(target, eye)
        mine = follower.final(own)
        assert mine.image.shape == (90, 120, 3) and not follower.following
        lead.annotate("check this flange", target)
        deadline = time.monotonic() + 30
        while not (follower.annotations and {p["name"] for p in follower.participants} == {"pat", "fay"}):
            assert time.monotonic() < deadline, (follower.annotations, follower.participants)
            time.sleep(0.05)
        assert follower.annotations[0]["text"] == "check this flange"
        assert admin_review_view(url, started["review"]["id"])["camera"]["eye"] == pytest.approx(eye)

        # A pointer and a saved view reach the other; the free follower jumps to the view.
        lead.point(target)
        lead.save_view("flange")
        wait_until(lambda: follower.saved_views and lead.participant_id in follower.pointers)
        assert follower.saved_views[-1]["name"] == "flange"
        assert follower.pointers[lead.participant_id]["position"] == pytest.approx(target)
        follower.jump(follower.saved_views[-1]["id"])
        jumped = follower.final(follower.camera.seq + 1)
        assert follower.camera.eye == pytest.approx(eye) and jumped.header.camera_seq == follower.camera.seq
        assert jumped.image.shape == (90, 120, 3) and not follower.following

        # The presenter hands over: the follower drives the shared view, pat follows it.
        lead.handover(follower.participant_id)
        wait_until(lambda: follower.role == "presenter" and lead.following)
        follower.next_frame()  # the shared view, now its own to drive
        eye2, _ = orbit_eye(tuple(lead.model_info["bounds"]), 2.6)
        seq2 = follower.set_camera(eye2, target)
        followed = lead.final(seq2)
        # The shared view has the new presenter's window now (the others letterbox it).
        assert lead.camera.eye == pytest.approx(eye2) and followed.image.shape == (90, 120, 3)
        with pytest.raises(VastrayError):
            lead.set_camera(eye, target)


def test_orthographic_views(url: str) -> None:
    """An orthographic camera over REST and over the stream: its picks go along the
    renderer's parallel rays, which start behind the model (the client's Camera computes
    the same rays); a follower in a review gets the presenter's projection; a bad one is
    refused with the field named."""
    from vastray.camera import Camera

    with Client(url) as vr:
        model = vr.model(vr.wait(vr.build("scene:plant:20000:5")).model_id)
        size = {"width": 160, "height": 120}
        persp = vr.render(model, camera=size)
        ortho = vr.render(model, camera={**size, "projection": "orthographic"})
        assert ortho.complete and np.abs(ortho.image.astype(int) - persp.image.astype(int)).mean() > 3
        eye, target = orbit_eye(model.bounds, 0.7)
        # The eye inside the model's box: an orthographic view still sees all of it.
        inside = tuple(np.asarray(target) + 0.2 * (np.asarray(eye) - np.asarray(target)))
        camera = {**size, "eye": inside, "target": target, "projection": "orthographic"}
        points = [(40.5, 30.5), (80.5, 60.5), (120.5, 90.5)]
        picked = vr.pick(model, points=points, camera=camera)
        cam = Camera(inside, target, width=160, height=120, projection="orthographic")
        origins, directions = cam.image_rays(np.asarray(points), model.bounds)
        rays = [(tuple(o), tuple(d)) for o, d in zip(origins.tolist(), directions.tolist(), strict=True)]
        along = vr.pick(model, rays=rays)
        assert [h.triangle for h in picked] == [h.triangle for h in along]
        assert sum(h.hit for h in picked) >= 2
        with pytest.raises(VastrayError) as err:
            vr.render(model, camera={**size, "projection": "isometric"})
        assert err.value.status == 422 and "projection" in str(err.value)

        started = vr.start_review(model, title="parallel")
    with (
        Client(started["presenter_url"]) as pat,
        Client(started["join_url"]) as fay,
        pat.join(name="pat", viewport=(160, 100)) as lead,
        fay.join(name="fay", viewport=(160, 100)) as follower,
    ):
        seq = lead.set_camera(eye, target)
        perspective = lead.final(seq)
        seq = lead.set_camera(eye, target, projection="orthographic")
        parallel = lead.final(seq)
        assert lead.camera.projection == "orthographic"
        assert np.abs(parallel.image.astype(int) - perspective.image.astype(int)).mean() > 3
        got = follower.final(seq)
        assert follower.camera.projection == "orthographic" and np.array_equal(got.image, parallel.image)
        lead.set_camera(target, eye)  # keeps the projection it has
        assert lead.camera.projection == "orthographic"


def test_a_section_box_keeps_what_lies_in_it(url: str) -> None:
    """A section box (`vastray.schemas.section_box`: six planes) in REST picks and
    renders and in a live view (`set_section_box`): every full-detail hit lies in the
    box, where the whole model hides it from outside; the live view's picks equal the
    REST ones with the same planes, and taking the planes away gives the whole model."""
    with Client(url) as vr:
        model = vr.model(vr.wait(vr.build("scene:plant:20000:5")).model_id)
        lo, hi = (np.asarray(b) for b in model.bounds)
        size = float(np.linalg.norm(hi - lo))
        bounds = (tuple(lo + 0.2 * (hi - lo)), tuple(lo + 0.8 * (hi - lo)))  # the middle of the plant
        box_lo, box_hi = (np.asarray(b) for b in bounds)
        margin = 0.01 * size
        box = section_box(*bounds, margin=margin)
        assert len(box) == 6
        centre = (box_lo + box_hi) / 2
        away = np.array([0.8, 0.5, 0.6]) / np.linalg.norm([0.8, 0.5, 0.6])
        eye, target = tuple((centre + 2.0 * size * away).tolist()), tuple(centre.tolist())
        camera = {"width": 160, "height": 120, "eye": eye, "target": target, "fov": 16}
        points = [(x + 0.5, y + 0.5) for y in range(2, 120, 4) for x in range(2, 160, 4)]
        whole = vr.pick(model, points=points, camera=camera)
        cut = vr.pick(model, points=points, camera=camera, sections=box)
        slack = margin + 1e-4 * size

        def in_box(h: Any) -> bool:
            p = np.asarray(h.position)
            return bool(np.all(p >= box_lo - slack) and np.all(p <= box_hi + slack))

        assert sum(h.hit for h in cut) >= 20 and all(in_box(h) for h in cut if h.hit)
        assert sum(h.hit and not in_box(h) for h in whole) >= 20, "the whole model should hide the inside"
        rendered = vr.render(model, camera=camera, sections=box)
        plain = vr.render(model, camera=camera)
        assert np.abs(rendered.image.astype(int) - plain.image.astype(int)).mean() > 3

        # The stream picks 64 points at a time: those that hit in the box, and those that
        # hit outside it without the box.
        chosen = [i for i, h in enumerate(cut) if h.hit][:32]
        chosen += [i for i, h in enumerate(whole) if h.hit and not in_box(h) and i not in chosen][:32]
        sample = [points[i] for i in chosen]
        with vr.view(model, viewport=(160, 120)) as view:
            view.set_section_box(bounds, margin=margin)
            view.final(view.set_camera(eye, target, fov=16))
            assert [h.triangle for h in view.pick(sample)] == [cut[i].triangle for i in chosen]
            view.set_sections([])
            view.final(view.set_camera(eye, target, fov=16))
            assert [h.triangle for h in view.pick(sample)] == [whole[i].triangle for i in chosen]
    with pytest.raises(ValueError, match="lo <= hi"):
        section_box((0, 0, 1), (1, 1, 0))
    with pytest.raises(ValueError, match="lo <= hi"):
        section_box((0, 0, 0), (1, 1, 1), margin=-0.6)  # a margin that leaves nothing
    with pytest.raises(ValueError, match="finite"):
        section_box((0, 0, 0), (1, 1, float("nan")))


def wait_until(condition: Any, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "not within the time allowed"
        time.sleep(0.05)


def admin_review_view(url: str, review_id: str) -> dict:
    with Client(url) as admin:
        return admin.review(review_id)["view"]


def test_a_view_reconnects_after_a_server_restart(tmp_path: Path) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = ServerProcess(tmp_path / "data", "--no-demo", port=port).start()
    try:
        with Client(f"{server.url}/?key={server.key}") as vr:
            job = vr.wait(vr.build("scene:spheres:4000:2", layout="smaller", tier_width=0))
            # The smaller layout (compact blocks) and, over it, no tiers: the same views.
            assert job.options["compact_triangles"] is True and job.options["tier_width"] == 0
            assert job.options["quantized_splits"] is True and "traversal_cost" not in job.options
            with vr.view(job.model_id, viewport=(96, 64)) as view:
                eye, target = orbit_eye(tuple(view.model_info["bounds"]), 0.4)
                seq = view.set_camera(eye, target)
                before = view.final()
                assert before.header.camera_seq == seq
                server.stop()
                server.start()
                # The view reconnects by itself; its camera comes along in the new hello.
                deadline = time.monotonic() + 60
                while True:
                    frame = view.next_frame(60)
                    if frame.final or time.monotonic() > deadline:
                        break
                assert frame.final and frame.image.shape == (64, 96, 3)
                assert np.abs(frame.image.astype(int) - before.image.astype(int)).mean() < 2
                assert view._async.connects == 2
                # Told why the first connection closed (viewers get a close message on shutdown).
                assert any(e["type"] == "closing" and "shutting down" in e["reason"] for e in view.events)
    finally:
        server.stop()
