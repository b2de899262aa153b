"""The streaming protocol (docs/PROTOCOL.md), shared by the server and the clients: the
binary frame header and the JSON messages of each direction.

One WebSocket per viewer at `/api/stream`. The client speaks first (`hello`, with its
credential and the model), the server answers `welcome`; then the client sends camera,
viewport and quality updates whenever it likes (the latest camera wins) and acknowledges
each frame it has shown, and the server sends binary frames (a fixed little-endian
header, then a JPEG or PNG) and JSON events.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Annotated, Any, Literal, get_args

from pydantic import BaseModel, Field, TypeAdapter

from vastray.schemas import MAX_IMAGE_SIDE, ProjectionName, Quality, SectionPlane, ShadingName, Strict, Vec3

PROTOCOL_VERSION = 1
FRAME_MAGIC = b"VRF1"

# Frame flags.
FLAG_COMPLETE = 1  # nothing this view needs at its accuracy was missing
FLAG_FINAL = 2  # the last refinement pass: the server goes idle on this view
FLAG_MOVING = 4  # rendered while the camera moved (reduced scale or accuracy)
FLAG_SCREENSHOT = 8  # the lossless image a `screenshot` message asked for

FORMAT_JPEG, FORMAT_PNG = 0, 1
FORMAT_NAMES = {FORMAT_JPEG: "jpeg", FORMAT_PNG: "png"}

_HEADER = struct.Struct("<4sHBBIIHHHHffffd")
HEADER_SIZE = _HEADER.size  # 48


@dataclass(frozen=True)
class FrameHeader:
    """What precedes every image on the wire (48 bytes, little endian)."""

    frame: int  # per-connection frame number, increasing
    camera_seq: int  # the `seq` of the camera message this frame answers
    width: int  # of the image as encoded (the viewport times the scale)
    height: int
    format: int  # FORMAT_JPEG or FORMAT_PNG
    flags: int
    pass_number: int  # 0 while moving; 1, 2, ... for the refinement passes of a still view
    render_ms: float
    encode_ms: float
    pixels_of_error: float  # the accuracy this frame was rendered at
    scale: float  # resolution scale against the viewport (1 when still)
    sent_at_ms: float  # server clock, ms since the Unix epoch

    @property
    def complete(self) -> bool:
        return bool(self.flags & FLAG_COMPLETE)

    @property
    def final(self) -> bool:
        return bool(self.flags & FLAG_FINAL)

    @property
    def moving(self) -> bool:
        return bool(self.flags & FLAG_MOVING)

    @property
    def format_name(self) -> str:
        return FORMAT_NAMES[self.format]

    def pack(self) -> bytes:
        return _HEADER.pack(
            FRAME_MAGIC,
            HEADER_SIZE,
            self.format,
            self.flags,
            self.frame,
            self.camera_seq,
            self.width,
            self.height,
            self.pass_number,
            0,
            self.render_ms,
            self.encode_ms,
            self.pixels_of_error,
            self.scale,
            self.sent_at_ms,
        )

    @classmethod
    def unpack(cls, data: bytes | memoryview) -> FrameHeader:
        if len(data) < HEADER_SIZE:
            raise ValueError(
                f"a frame message of {len(data)} bytes is shorter than its {HEADER_SIZE}-byte header"
            )
        (
            magic,
            size,
            fmt,
            flags,
            frame,
            seq,
            width,
            height,
            pass_number,
            _,
            render_ms,
            encode_ms,
            poe,
            scale,
            sent,
        ) = _HEADER.unpack_from(data)
        if magic != FRAME_MAGIC:
            raise ValueError(f"not a vastray frame (magic {magic!r})")
        if size != HEADER_SIZE:
            raise ValueError(f"frame header of {size} bytes: another protocol version")
        return cls(frame, seq, width, height, fmt, flags, pass_number, render_ms, encode_ms, poe, scale, sent)


# ---- client -> server -------------------------------------------------------------------


class CameraState(Strict):
    """A camera in world coordinates (double precision) with the sequence number the
    client gave it; frames say which seq they answer."""

    seq: int = Field(0, ge=0, lt=2**32)
    eye: Vec3
    target: Vec3
    up: Vec3 = (0.0, 1.0, 0.0)
    fov: float = Field(45.0, gt=0.0, lt=180.0)
    projection: ProjectionName = "perspective"


class Viewport(Strict):
    width: int = Field(960, ge=1, le=MAX_IMAGE_SIDE)
    height: int = Field(540, ge=1, le=MAX_IMAGE_SIDE)
    device_pixel_ratio: float = Field(1.0, gt=0.0, le=8.0)


class StreamQuality(Quality):
    """Render parameters plus what the stream does with them."""

    jpeg_quality: int = Field(80, ge=10, le=100)
    refine: bool = True  # refine a still view (full scale, accuracy, anti-aliasing), then idle
    target_fps: float = Field(16.0, ge=1.0, le=120.0)  # while moving (paper 002's "acceptable")
    min_scale: float = Field(0.25, gt=0.0, le=1.0)  # the lowest resolution scale while moving
    max_moving_poe: float = Field(8.0, ge=0.0, le=1e6)  # how far PoE may rise while moving
    aa_passes: int = Field(4, ge=1, le=64)  # jittered passes averaged when refining
    auto_accuracy: bool = False  # measure the accuracy of a still, finished view by itself


class Hello(Strict):
    type: Literal["hello"]
    protocol: int
    model: str
    token: str | None = None  # the API key, a viewing token or a review token (or ?token= in the URL)
    review: str | None = None  # join this design review (its model must be `model`)
    name: str | None = Field(None, max_length=80)  # how other participants see this one
    session: str | None = None  # resume a session after a reconnect
    viewport: Viewport | None = None
    camera: CameraState | None = None
    quality: StreamQuality | None = None


class CameraMessage(CameraState):
    type: Literal["camera"]


class ViewportMessage(Viewport):
    type: Literal["viewport"]


class QualityMessage(Strict):
    type: Literal["quality"]
    # Only the fields given change.
    shading: ShadingName | None = None
    pixels_of_error: float | None = Field(None, ge=0.0, le=1e6)
    ao_samples: int | None = Field(None, ge=1, le=1024)
    jpeg_quality: int | None = Field(None, ge=10, le=100)
    refine: bool | None = None
    target_fps: float | None = Field(None, ge=1.0, le=120.0)
    min_scale: float | None = Field(None, gt=0.0, le=1.0)
    max_moving_poe: float | None = Field(None, ge=0.0, le=1e6)
    aa_passes: int | None = Field(None, ge=1, le=64)
    auto_accuracy: bool | None = None


class SectionsMessage(Strict):
    type: Literal["sections"]
    planes: list[SectionPlane] = Field(default_factory=list, max_length=6)


class HighlightMessage(Strict):
    """Parts the renderer shades as highlighted (ids of the model's part table)."""

    type: Literal["highlight"]
    parts: list[int] = Field(default_factory=list, max_length=4096)


class AccuracyMessage(Strict):
    """Measure what the current accuracy costs on this view against full detail."""

    type: Literal["accuracy"]


class FollowMessage(Strict):
    """In a review: follow the presenter's view, or navigate freely."""

    type: Literal["follow"]
    follow: bool


class PointerMessage(Strict):
    """In a review: a 3D point every participant sees (None: take it away)."""

    type: Literal["pointer"]
    position: Vec3 | None = None


class AnnotateMessage(Strict):
    """In a review: a note pinned at a 3D point, kept with the review."""

    type: Literal["annotate"]
    text: str = Field(min_length=1, max_length=2000)
    position: Vec3


class SaveViewMessage(Strict):
    """In a review: keep this view (camera, sections, quality, highlight) under a name."""

    type: Literal["save_view"]
    name: str = Field(min_length=1, max_length=200)


class JumpMessage(Strict):
    """In a review: go to a saved view (the presenter moves everyone who follows)."""

    type: Literal["jump"]
    view: str = Field(max_length=64)


class RenameMessage(Strict):
    """In a review: the name other participants see."""

    type: Literal["rename"]
    name: str = Field(min_length=1, max_length=80)


class HandoverMessage(Strict):
    """In a review: the presenter hands the presenter role to another participant."""

    type: Literal["handover"]
    to: str = Field(max_length=64)


class AckMessage(Strict):
    """The client has shown frame `frame` (at most a couple of frames are unacknowledged)."""

    type: Literal["ack"]
    frame: int = Field(ge=0)


class PingMessage(Strict):
    type: Literal["ping"]
    t: float = 0.0  # echoed in the pong


class ScreenshotMessage(Strict):
    """A lossless PNG of the finished (complete, refined) view."""

    type: Literal["screenshot"]
    id: str = Field("", max_length=64)


class PickMessage(Strict):
    """Full-detail ray queries through image points (pixels, top-left origin) of the
    camera of the frame `frame` the client shows (or the current camera)."""

    type: Literal["pick"]
    id: str = Field("", max_length=64)
    points: list[tuple[float, float]] = Field(min_length=1, max_length=64)
    camera: CameraState | None = None
    # The image the points are pixels of (default: the view's viewport).
    width: int | None = Field(None, ge=1, le=MAX_IMAGE_SIDE)
    height: int | None = Field(None, ge=1, le=MAX_IMAGE_SIDE)


class ByeMessage(Strict):
    type: Literal["bye"]


ClientMessage = Annotated[
    CameraMessage
    | ViewportMessage
    | QualityMessage
    | AckMessage
    | PingMessage
    | ScreenshotMessage
    | PickMessage
    | SectionsMessage
    | HighlightMessage
    | AccuracyMessage
    | FollowMessage
    | PointerMessage
    | AnnotateMessage
    | SaveViewMessage
    | JumpMessage
    | HandoverMessage
    | RenameMessage
    | ByeMessage,
    Field(discriminator="type"),
]
CLIENT_MESSAGE = TypeAdapter(ClientMessage)
# Every message type a client may send (the union's `type` literals, in its order).
CLIENT_TYPES = tuple(
    get_args(m.model_fields["type"].annotation)[0] for m in get_args(get_args(ClientMessage)[0])
)


# ---- server -> client (JSON) --------------------------------------------------------------


class Welcome(BaseModel):
    type: Literal["welcome"] = "welcome"
    protocol: int = PROTOCOL_VERSION
    session: str
    resumed: bool
    model: dict[str, Any]
    camera: CameraState
    viewport: Viewport
    quality: StreamQuality
    sections: list[SectionPlane] = Field(default_factory=list)
    highlight: list[int] = Field(default_factory=list)
    limits: dict[str, Any]
    review: dict[str, Any] | None = None  # id, title, role, participant, presenter, following


class StatsEvent(BaseModel):
    type: Literal["stats"] = "stats"
    frame: int
    camera_seq: int
    camera: CameraState  # the camera this frame shows (a follower's page did not send it)
    pass_number: int
    moving: bool
    complete: bool
    final: bool
    width: int
    height: int
    scale: float
    pixels_of_error: float
    render_ms: float
    encode_ms: float
    queue_ms: float  # from the camera's arrival to the start of its render
    latency_ms: float  # from the camera's arrival to this frame's send
    bytes: int
    fps: float  # frames sent per second to this client, recently
    working_set_bytes: int
    pending_blocks: int
    cache_hit_rate: float
    voxel_hits: int
    rays: int


class ErrorEvent(BaseModel):
    type: Literal["error"] = "error"
    code: str
    message: str
    fatal: bool = False  # the server closes the connection after a fatal error


def parse_client_message(data: str | bytes) -> Any:
    """A client message, or ValueError with a message for the client."""
    import json

    try:
        raw = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"malformed JSON: {exc}") from None
    if not isinstance(raw, dict):
        raise ValueError("a message is a JSON object with a 'type'")
    kind = raw.get("type")
    if kind not in CLIENT_TYPES:
        raise ValueError(f"unknown message type {kind!r}; expected one of {', '.join(CLIENT_TYPES)}")
    from pydantic import ValidationError

    try:
        return CLIENT_MESSAGE.validate_python(raw)
    except ValidationError as exc:
        from vastray.schemas import describe_errors

        # The union's tag leads each error's location, and the message names the type
        # already: "camera: projection: ...", not "camera: camera.projection: ...".
        errors = []
        for e in exc.errors():
            loc = tuple(e.get("loc", ()))
            errors.append({**e, "loc": loc[1:]} if loc[:1] == (kind,) else e)
        raise ValueError(f"{kind}: {describe_errors(errors)}") from None
