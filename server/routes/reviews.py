"""Design reviews: create one (with its presenter and join links), list, look at one
(its participants now, its annotations and saved views), delete."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response
from pydantic import Field

from vastray.protocol import CameraState, StreamQuality
from vastray.schemas import SectionPlane, Strict
from vastray.server.auth import credential
from vastray.server.deps import Admin, state_of
from vastray.server.errors import ApiError
from vastray.server.reviews import new_review_id, review_urls
from vastray.server.views import camera_problem

router = APIRouter(prefix="/api/reviews", tags=["reviews"])


class ReviewView(Strict):
    """Where the shared view starts: what a saved view keeps."""

    camera: CameraState
    quality: StreamQuality | None = None
    sections: list[SectionPlane] = Field(default_factory=list, max_length=6)
    highlight: list[int] = Field(default_factory=list, max_length=4096)


class ReviewRequest(Strict):
    model: str
    title: str = Field("review", max_length=200)
    ttl_seconds: float = Field(
        7 * 24 * 3600.0, gt=0, le=365 * 24 * 3600.0, description="how long the links work"
    )
    view: ReviewView | None = Field(
        None,
        description="where the shared view starts (the page sends what it shows); "
        "without it, the first participant's camera",
    )


def base_url(request: Request) -> str:
    public = state_of(request).settings.public_url
    return public.rstrip("/") if public else str(request.base_url).rstrip("/")


def review_or_404(request: Request, review_id: str) -> dict[str, Any]:
    review = state_of(request).registry.review(review_id)
    if review is None:
        raise ApiError(404, "review_not_found", f"no review {review_id!r}")
    return review


@router.post("", status_code=201, summary="Start a review of a model: a presenter link and a join link")
def create_review(body: ReviewRequest, request: Request, _: Admin) -> dict[str, Any]:
    state = state_of(request)
    state.store.row(body.model, ready=True)
    problem = camera_problem(body.view.camera) if body.view is not None else None
    if problem:
        raise ApiError(422, "invalid_camera", f"view.{problem}")
    review_id = new_review_id()
    start = body.view.model_dump(exclude_none=True) if body.view is not None else None
    state.registry.add_review(review_id, body.model, body.title, start)
    presenter, _row = state.auth.issue(
        "review", review_id, body.ttl_seconds, role="presenter", label="presenter"
    )
    follower, row = state.auth.issue("review", review_id, body.ttl_seconds, role="follower", label="join")
    return {
        "review": {"id": review_id, "model": body.model, "title": body.title, "expires_at": row.expires_at},
        "presenter_token": presenter,
        "join_token": follower,
        **review_urls(base_url(request), review_id, presenter, follower),
    }


@router.get("", summary="Reviews")
def list_reviews(request: Request, _: Admin) -> list[dict[str, Any]]:
    return [
        {"id": r["id"], "model": r["model_id"], "title": r["title"], "created_at": r["created_at"]}
        for r in state_of(request).registry.reviews()
    ]


@router.get("/{review_id}", summary="A review: its model, who is in it now, annotations, saved views")
def get_review(review_id: str, request: Request) -> dict[str, Any]:
    state = state_of(request)
    grant = state.auth.grant(credential(request))
    if not (grant.admin or (grant.scope == "review" and grant.subject == review_id)):
        raise ApiError(403, "forbidden", f"this token does not grant access to review {review_id}")
    review = review_or_404(request, review_id)
    live = state.streams.reviews.get(review_id)
    return {
        "id": review_id,
        "model": review["model_id"],
        "title": review["title"],
        "created_at": review["created_at"],
        "participants": [p.describe() for p in live.participants.values()] if live else [],
        # Where the shared view is now; with nobody in it, where it was left (or, before
        # anyone joined, where it starts).
        "view": live.shared.state() if live and live.shared else review["state"] or None,
        "annotations": state.registry.annotations(review_id),
        "views": [
            {"id": v["id"], "name": v["name"], **v["state"]} for v in state.registry.saved_views(review_id)
        ],
        "role": grant.role if not grant.admin else "presenter",
    }


@router.delete("/{review_id}", status_code=204, summary="End a review and revoke its links")
def delete_review(review_id: str, request: Request, _: Admin) -> Response:
    review_or_404(request, review_id)
    state_of(request).registry.delete_review(review_id)
    return Response(status_code=204)
