"""The wire schemas: what the REST API and the streaming protocol accept and return,
shared by the server (vastray.server) and the Python client (vastray.client).

Render parameters and frame statistics are the native structs' fields under the same
names and with the same defaults (`native.RenderParams()`, `native.FrameStats.fields`),
so a setting is spelled one way in the Python API, the CLI, REST and the protocol.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator

from vastray import native
from vastray.camera import PROJECTIONS, STANDARD_VIEWS, unit_up
from vastray.renderer import RENDER_PARAM_FIELDS, render_params

_DEFAULTS = native.RenderParams()
MAX_IMAGE_SIDE: int = native.MAX_IMAGE_SIDE


def _finite(v: tuple[float, float, float]) -> tuple[float, float, float]:
    if not all(math.isfinite(x) for x in v):
        raise ValueError("every component must be a finite number")
    return v


Vec3 = Annotated[tuple[float, float, float], AfterValidator(_finite)]


def _unit(v: tuple[float, float, float]) -> tuple[float, float, float]:
    if not any(v):  # (finite already: Vec3)
        raise ValueError("up vector has zero length")
    return unit_up(v)


UnitVec3 = Annotated[Vec3, AfterValidator(_unit)]
UP_DESCRIPTION = "which way is up in the model (default +y; CAD exports and scans are often z-up: [0, 0, 1])"

ShadingName = Literal["normal", "headlight", "sun", "ao", "indirect"]
assert set(ShadingName.__args__) == set(native.SHADING_MODES)  # one list of modes
StandardViewName = Literal["iso", "front", "back", "left", "right", "top", "bottom"]
assert list(StandardViewName.__args__) == list(STANDARD_VIEWS)  # one list of views
ProjectionName = Literal["perspective", "orthographic"]
assert list(ProjectionName.__args__) == list(PROJECTIONS)
# The length units a model's coordinates may be said to be in (meshes do not say).
UnitName = Literal["mm", "cm", "m", "km", "in", "ft"]


def describe_errors(errors: list[Any]) -> str:
    """'camera.fov: Input should be less than 180; quality.shading: …' from pydantic's
    errors, for people."""
    parts = []
    for e in errors:
        where = ".".join(str(p) for p in e.get("loc", ()) if p not in ("body", "query", "path"))
        message = str(e.get("msg", "invalid")).removeprefix("Value error, ")
        parts.append(f"{where}: {message}" if where else message)
    return "; ".join(parts)


class Strict(BaseModel):
    # Unknown fields are an error, not silently dropped: a misspelt setting should say so.
    # No number a client sends may be NaN or infinite, and saying so names the reason (a
    # NaN field of view would otherwise be 'Input should be less than 180').
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class CameraSpec(Strict):
    """A camera in world coordinates (double precision). Without an eye the camera
    frames the whole model from a three-quarter view; without a target it looks at the
    model's centre; without an up it takes the model's (`ModelInfo.up`). An orthographic
    one looks along the view from every pixel, over the extent the perspective view has
    at the target."""

    eye: Vec3 | None = None
    target: Vec3 | None = None
    up: Vec3 | None = None
    view: StandardViewName | None = Field(
        None, description="a standard view of the whole model, upright about its up (without eye and target)"
    )
    fov: float = Field(45.0, gt=0.0, lt=180.0, description="vertical field of view, degrees")
    width: int = Field(960, ge=1, le=MAX_IMAGE_SIDE)
    height: int = Field(540, ge=1, le=MAX_IMAGE_SIDE)
    projection: ProjectionName = Field(
        "perspective",
        description="orthographic: parallel rays over the extent the perspective view has at the target",
    )

    @model_validator(mode="after")
    def _check(self) -> CameraSpec:
        if self.eye is not None and self.target is not None:
            d = [t - e for t, e in zip(self.target, self.eye, strict=True)]
            if not any(d):
                raise ValueError("eye and target coincide: the view direction has zero length")
        if self.up is not None and not any(self.up):
            raise ValueError("up vector has zero length")
        if self.view is not None and (self.eye is not None or self.target is not None):
            raise ValueError("a standard view frames the whole model: give it without eye and target")
        return self

    @property
    def pixels(self) -> int:
        return self.width * self.height


class Quality(Strict):
    """Render parameters (native.RenderParams): the same names and defaults."""

    shading: ShadingName = _DEFAULTS.shading  # type: ignore[assignment]
    pixels_of_error: float = Field(_DEFAULTS.pixels_of_error, ge=0.0, le=1e6)
    ao_samples: int = Field(_DEFAULTS.ao_samples, ge=1, le=1024)
    ao_distance: float = Field(_DEFAULTS.ao_distance, ge=0.0)
    solid_angle: float = Field(_DEFAULTS.solid_angle, le=2 * math.pi)
    sun_direction: Vec3 = tuple(_DEFAULTS.sun_direction)  # type: ignore[assignment]
    packets: Literal[0, 1, 4, 16] = _DEFAULTS.packets  # type: ignore[assignment]

    @model_validator(mode="after")
    def _check(self) -> Quality:
        self.to_native()  # the native checks, with their messages (e.g. a zero sun direction)
        return self

    def to_native(self, threads: int = 0) -> native.RenderParams:
        # Subclasses add fields of their own (a stream's frame rate): pass on the renderer's.
        fields = {k: getattr(self, k) for k in type(self).model_fields if k in RENDER_PARAM_FIELDS}
        return render_params(threads=threads, **fields)


# Every Quality field is a RenderParams field (tile_size and threads are the server's).
assert set(Quality.model_fields) <= set(RENDER_PARAM_FIELDS)


class SectionPlane(Strict):
    """A clipping plane: geometry where dot(normal, p) + offset < 0 is cut away."""

    normal: Vec3
    offset: float = Field(allow_inf_nan=False)
    enabled: bool = True

    @model_validator(mode="after")
    def _check(self) -> SectionPlane:
        if not any(self.normal):
            raise ValueError("a section plane's normal has zero length")
        return self

    def native(self) -> tuple[float, float, float, float]:
        return (*self.normal, self.offset)


def section_box(lo: Sequence[float], hi: Sequence[float], margin: float = 0.0) -> list[SectionPlane]:
    """A section box, as CAD viewers have it: six planes that keep what lies within the
    box [lo - margin, hi + margin] (say a part's bounds, `PartInfo.bounds`) and cut away
    everything else. Each plane faces into the box, so its own offset moves that face."""
    if len(lo) != 3 or len(hi) != 3 or not all(math.isfinite(x) for x in (*lo, *hi, margin)):
        raise ValueError(f"a section box needs corners of 3 finite numbers and a finite margin: {lo}, {hi}")
    if not all(a - margin <= b + margin for a, b in zip(lo, hi, strict=True)):
        raise ValueError(f"a section box needs lo <= hi on every axis, margin included: {lo}, {hi}, {margin}")
    planes = []
    for axis in range(3):
        inward = [0.0, 0.0, 0.0]
        inward[axis] = 1.0  # keeps p[axis] >= lo[axis] - margin
        planes.append(SectionPlane(normal=tuple(inward), offset=-(lo[axis] - margin)))
        inward[axis] = -1.0  # keeps p[axis] <= hi[axis] + margin
        planes.append(SectionPlane(normal=tuple(inward), offset=hi[axis] + margin))
    return planes


def native_sections(planes: list[SectionPlane]) -> list[tuple[float, float, float, float]]:
    """The enabled planes as the renderers take them."""
    return [p.native() for p in planes if p.enabled]


class FullDetailQuality(Quality):
    """Quality of one-shot renders: full detail unless the request says otherwise."""

    pixels_of_error: float = Field(0.0, ge=0.0, le=1e6)


class RenderRequest(Strict):
    camera: CameraSpec = CameraSpec()
    quality: FullDetailQuality = FullDetailQuality()
    sections: list[SectionPlane] = Field(default_factory=list, max_length=6)
    format: Literal["png", "jpeg"] = "png"
    jpeg_quality: int = Field(90, ge=1, le=100)
    timeout: float = Field(60.0, gt=0.0, le=600.0, description="seconds to wait for the data the view needs")


class PickRequest(Strict):
    """Full-detail ray queries: image points of a camera, or world rays."""

    camera: CameraSpec | None = None
    points: list[tuple[float, float]] = Field(
        default_factory=list, max_length=4096, description="(x, y) in pixels from the image's top-left corner"
    )
    rays: list[tuple[Vec3, Vec3]] = Field(
        default_factory=list, max_length=4096, description="(origin, direction) in world coordinates"
    )
    timeout: float = Field(10.0, gt=0.0, le=120.0)
    sections: list[SectionPlane] = Field(default_factory=list, max_length=6)

    @model_validator(mode="after")
    def _check(self) -> PickRequest:
        if not self.points and not self.rays:
            raise ValueError("give points (with a camera) or rays")
        if self.points and self.camera is None:
            raise ValueError("points need the camera they were picked in")
        for origin, direction in self.rays:
            if not any(direction):
                raise ValueError(f"ray from {origin} has a zero-length direction")
        return self


class PickHit(BaseModel):
    hit: bool
    complete: bool  # False: the data this ray needs did not arrive within the timeout
    distance: float | None = None  # from the ray origin (the eye for points), world units
    position: tuple[float, float, float] | None = None
    normal: tuple[float, float, float] | None = None
    triangle: int | None = None  # the input's own triangle id
    part_id: int | None = None  # its part, an id of the model's part table
    part: str | None = None  # that part's name


class PartInfo(BaseModel):
    id: int
    name: str
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]]  # world coordinates
    triangles: int

    @classmethod
    def of(cls, part: Any) -> PartInfo:
        """From a `vastray.modelfile.ModelPart`."""
        return cls(id=part.id, name=part.name, bounds=(part.lo, part.hi), triangles=part.triangles)


class PartList(BaseModel):
    total: int  # parts that match the query
    parts: list[PartInfo]


class PickResponse(BaseModel):
    hits: list[PickHit]
    milliseconds: float


class FrameStatsOut(BaseModel):
    """native.FrameStats, field for field."""

    model_config = ConfigDict(extra="allow")

    @classmethod
    def of(cls, stats: native.FrameStats) -> FrameStatsOut:
        return cls(**stats.as_dict())


class LevelInfo(BaseModel):
    level: int | str
    blocks: int
    raw_bytes: int
    stored_bytes: int
    nodes: int | None = None
    voxels: int | None = None


ModelState = Literal["building", "ready", "deleting"]


class ModelInfo(BaseModel):
    id: str
    name: str
    state: ModelState
    created_at: float
    source: str | None = None
    job_id: str | None = None  # the build job that makes (or made) it
    file: str | None = None  # relative to the data directory
    triangles: int | None = None
    input_triangles: int | None = None
    degenerate: int | None = None
    bytes: int | None = None
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    lod_levels: int | None = None
    colours: bool | None = None
    part_ids: bool | None = None
    part_count: int = 0  # named parts stored in the model (GET .../parts lists them)
    levels: list[LevelInfo] | None = None
    build: dict[str, Any] | None = None  # build parameters and report
    in_use: int = 0  # viewers, renders and jobs using it now
    # Which way is up in the model (a unit vector): default cameras, framing and orbits
    # turn about it. Meshes come either way (CAD and scans are often z-up).
    up: Vec3 = (0.0, 1.0, 0.0)
    # The length unit of its coordinates, when someone has said (PATCH): measurements
    # are given in it. None: not said (most mesh formats do not store one).
    units: UnitName | None = None


JobState = Literal["queued", "running", "succeeded", "failed", "cancelled", "interrupted"]
TERMINAL_JOB_STATES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled", "interrupted"})


class JobInfo(BaseModel):
    id: str
    kind: Literal["build"] = "build"
    model_id: str | None
    name: str
    source: str
    state: JobState
    phase: str | None = None
    percent: float = 0.0
    eta_seconds: float | None = None
    message: str | None = None
    error: str | None = None
    options: dict[str, Any] = Field(default_factory=dict)
    report: dict[str, Any] | None = None
    created_at: float
    started_at: float | None = None
    finished_at: float | None = None
    log_tail: list[str] = Field(default_factory=list)


class BuildOptionsIn(Strict):
    """A build's options: a named layout (vastray/layouts.py), and any option given here
    over the layout's value."""

    memory: str | int | None = Field(None, description="memory budget, e.g. '2G' (default: the server's)")
    threads: int | None = Field(None, ge=0, le=1024, description="build threads (0: all cores)")
    layout: Literal["balanced", "smaller", "smallest"] = Field(
        "balanced",
        description="what the file is for: balanced (tiered: far views read least), smaller (compact "
        "triangle blocks, about 30 % smaller, lossless) or smallest (also untiered, quantized "
        "vertices, a coarser tree, LZ4 HC 9: 34-39 % of balanced, the same frame time for the same "
        "accuracy, a slower build); the options below override it",
    )
    quantized_splits: bool = Field(
        True, description="split planes on a 20-bit grid of their cell: 5 % smaller, the same images"
    )
    quantized_vertices: bool = Field(
        False,
        description="vertices on a 2^21-step grid of the model's box, bit-packed per block: smaller, "
        "lossy by at most one grid step, watertight",
    )
    compact_triangles: bool = Field(
        False,
        description="triangle blocks with bit-packed leaf lists, corners, ids and colours: about 30 % "
        "smaller, lossless, full-detail frames 4-12 % slower",
    )
    tier_width: float | None = Field(
        None,
        ge=0,
        le=16,
        description="coarseness tiers, octaves of LOD radius per tier (default 1): far views read "
        "the first tiers only; wider tiers or 0 (untiered) make smaller files and faster builds, "
        "and far views read more",
    )
    traversal_cost: float | None = Field(
        None,
        gt=0,
        le=64,
        description="the kd-tree's SAH cost of a node step in triangle tests (default 4): higher "
        "builds a coarser tree, faster and smaller, with slower LOD frames where rays end in leaves",
    )
    lz4_hc_level: int | None = Field(
        None,
        ge=0,
        le=12,
        description="LZ4 HC level of the blocks (default 0: LZ4's fast compressor): 1-12 make "
        "smaller blocks of the same format, read as fast, in a slower build",
    )
    voxel_errors: bool | None = Field(
        None,
        description="LOD nodes keep a bound on how far their voxel's box lies from its triangles, "
        "which their LOD test compares instead of the box's radius (default on, with quantized "
        "splits): at the same accuracy 0.61-0.85x the working set of the 10^8 plant's overview, "
        "up to 1.09x in nearer views of the 10^7 one (docs/FORMAT.md, Measured choices)",
    )


class JobRequest(Strict):
    """A build: from 'demo', 'scene:NAME:TRIANGLES:SEED', a mesh already in the data
    directory (relative path), or an upload."""

    source: str | None = None
    upload: str | None = None
    name: str | None = Field(None, max_length=200)
    up: UnitVec3 | None = Field(None, description=UP_DESCRIPTION)
    options: BuildOptionsIn = BuildOptionsIn()

    @model_validator(mode="after")
    def _check(self) -> JobRequest:
        if (self.source is None) == (self.upload is None):
            raise ValueError("give exactly one of source and upload")
        return self


class ModelRequest(Strict):
    """Register a model: a built model in the data directory (`path`), an uploaded
    built model (`upload`), or a mesh (either way), which starts a build job."""

    path: str | None = None
    upload: str | None = None
    name: str | None = Field(None, max_length=200)
    up: UnitVec3 | None = Field(None, description=UP_DESCRIPTION)
    options: BuildOptionsIn = BuildOptionsIn()

    @model_validator(mode="after")
    def _check(self) -> ModelRequest:
        if (self.path is None) == (self.upload is None):
            raise ValueError("give exactly one of path and upload")
        return self


class ModelPatch(Strict):
    """What an admin may change on a model: its name, which way is up (stored as a
    unit vector; views opened after the change start from it), and the length unit of
    its coordinates."""

    name: str | None = Field(None, min_length=1, max_length=200)
    up: UnitVec3 | None = Field(None, description=UP_DESCRIPTION)
    units: Literal[UnitName, ""] | None = Field(
        None, description='the length unit of the model\'s coordinates; "" to say none'
    )


class ModelCreated(BaseModel):
    model: ModelInfo
    job: JobInfo | None = None  # set when a mesh was registered: the build that makes it


class UploadInfo(BaseModel):
    id: str
    filename: str
    bytes: int
    kind: Literal["model", "mesh"]
    created: ModelCreated | None = None  # when registration was asked for with the upload


class TokenRequest(Strict):
    ttl_seconds: float = Field(24 * 3600.0, gt=0.0, le=365 * 24 * 3600.0)
    label: str | None = Field(None, max_length=200)


class TokenInfo(BaseModel):
    token: str
    scope: Literal["model", "review"]
    subject: str
    expires_at: float
    label: str | None = None


class ErrorBody(BaseModel):
    code: str
    message: str
    detail: Any = None


class ErrorResponse(BaseModel):
    error: ErrorBody
