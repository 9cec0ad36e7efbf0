"""The job parameters a client sends (JSON), validated field by field, and their engine form.

Most parameters are flat; the engine's optional steps are objects: ``orient`` (how an image stack lies),
``preprocess`` (the paper's slice preprocessing, off unless given), ``defect`` (the one-sided defect and its
mirrored template, off unless given), ``roi`` (a box the scan or label map is cropped to first), and ``body`` and
``islands`` (bone inside the body outline, speck removal: on unless sent as ``null``). ``labels`` (the upload is a
label map) and ``pieces`` (a CT's N largest bone pieces as parts) make a label job (``engine.labels``). The
engine's form of a request is a ``engine.job.JobSpec`` (``JobParams.job_spec``), checked by the engine's rules when
the request is validated and stored with the job, so the worker runs what the API accepted. Left out, every step
keeps the engine's default (``engine.params.ReconParams()``).

Part of the job's contract, so shared: the API validates a request with it and stores both forms, a PACS routing
rule carries one (``core.pacs.routing``), and the worker converts a job recorded by an older release with it.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictInt, StrictStr, field_validator, model_validator

from engine.defect.params import DEFAULT_MAX_FACES, DefectParams
from engine.job.spec import InputSpec, JobSpec
from engine.params import (
    DEFAULT_SPECK_VOXELS,
    FLOAT32_MAX,
    INT32_MAX,
    SPACING_MM_MAX,
    SPACING_MM_MIN,
    BodyMaskParams,
    DecimateParams,
    ExportParams,
    IsoParams,
    OrientParams,
    PiecesParams,
    PreprocessParams,
    ReconParams,
    RoiParams,
    SmoothParams,
    check_spacing_zyx_mm,
    decimate_of,
    islands_of,
    spacing_order_warning,
)

# the engine's defaults, so that a job that leaves an option out gets what the CLI and the library get
_ORIENT, _BODY, _DECIMATE, _SMOOTH, _EXPORT = (
    OrientParams(),
    BodyMaskParams(),
    DecimateParams(),
    SmoothParams(),
    ExportParams(),
)
# pieces of a job's parameters that may be sent as null to switch an on-by-default step off
SWITCHES = ("body", "islands")


class _Group(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class OrientJobParams(_Group):
    """How an image stack lies in the patient (DICOM ignores it: its headers place it)."""

    first_slice: Literal["superior", "inferior"] = Field(
        default=_ORIENT.first_slice,  # type: ignore[arg-type]
        description="which end of the stack the first slice is: superior (most CT series), or inferior (stacks "
        "sorted by ascending position, e.g. from 3D Slicer or ITK)",
    )
    flip_lr: bool = Field(default=_ORIENT.flip_lr, description="the image's left is the patient's left")
    flip_ap: bool = Field(default=_ORIENT.flip_ap, description="the image's top is posterior")


class PreprocessJobParams(_Group):
    """The paper's slice preprocessing, per slice in this order: threshold, area opening, Canny (each off unless
    given)."""

    threshold: float | None = Field(
        default=None, ge=-FLOAT32_MAX, le=FLOAT32_MAX, description="set samples below this value to the minimum"
    )
    area_opening_px: int | None = Field(
        default=None, ge=1, le=INT32_MAX, description="remove bright specks below this many pixels per slice"
    )
    canny_sigma: float | None = Field(
        default=None, gt=0, le=1e4, description="replace each slice by its Canny edge map with this sigma"
    )


class BodyJobParams(_Group):
    """Bone inside the patient's body outline only (HU data); send ``"body": null`` to keep bone outside it."""

    outline_hu: float = Field(
        default=_BODY.outline_hu,
        ge=-FLOAT32_MAX,
        le=FLOAT32_MAX,
        description="the body outline's air/tissue threshold (HU)",
    )


class IslandJobParams(_Group):
    """Speck removal; send ``"islands": null`` to keep pieces of any size (``keep_largest`` still applies)."""

    min_volume_voxels: float = Field(
        default=DEFAULT_SPECK_VOXELS,
        ge=0,
        le=FLOAT32_MAX,
        description="drop pieces smaller than this many voxels' volume (0: no limit) unless min_island_mm3 is given",
    )


class DefectJobParams(_Group):
    """Find the bone's one-sided defect and make its mirrored fill template (``engine.defect``): ``implant.stl``
    (patient frame of model.stl, mm), ``defect.json`` (its size, place and the symmetry plane, or why there is
    none), and the template as its own coloured node in the GLB files. Send ``"defect": {}`` for the defaults."""

    side: Literal["left", "right"] | None = Field(
        default=None, description="a hint: the patient's side the defect is on (default: either)"
    )
    point_lps_mm: list[float] | None = Field(
        default=None,
        min_length=3,
        max_length=3,
        description="a hint: a point in or next to the defect, [x, y, z] mm in the patient frame (LPS) of model.stl",
    )
    point_radius_mm: float = Field(
        default=40.0, gt=0, le=500, description="how far from point_lps_mm the defect may lie (mm)"
    )
    min_volume_mm3: float | None = Field(
        default=None, ge=0, le=FLOAT32_MAX, description="smallest defect reported (mm³; default: a 15 mm plug)"
    )
    max_faces: int = Field(
        default=DEFAULT_MAX_FACES, ge=100, le=INT32_MAX, description="the template's triangles at most"
    )

    def engine(self) -> DefectParams:
        """The engine's form."""
        data = self.model_dump()
        data["point_lps_mm"] = None if self.point_lps_mm is None else tuple(self.point_lps_mm)
        return DefectParams(**data)


class RoiJobParams(_Group):
    """A region of interest: the scan (or label map) is cropped to this box before anything runs."""

    box: list[list[float]] = Field(
        min_length=3,
        max_length=3,
        description="three [lo, hi] ranges: voxel indices [z, y, x] (lo inclusive, hi exclusive) with units "
        '"voxels", or patient-frame (LPS) [x, y, z] in mm with units "mm"',
    )
    units: Literal["voxels", "mm"] = Field(default="voxels", description="what the box's numbers are")

    @model_validator(mode="after")
    def _engine(self) -> RoiJobParams:
        self.engine()  # the engine's own checks (ValueError: 422 naming roi)
        return self

    def engine(self) -> RoiParams:
        """The engine's form."""
        if any(len(r) != 2 for r in self.box):
            raise ValueError(f"each range of box is [lo, hi], got {self.box}")
        (z0, z1), (y0, y1), (x0, x1) = self.box
        return RoiParams(((z0, z1), (y0, y1), (x0, x1)), units=self.units)


class JobParams(BaseModel):
    """Reconstruction parameters of a job (all optional; defaults are the paper's best combination).

    The iso level: ``iso`` in the scan's units, or a HU ``preset`` (DICOM is in HU; for image stacks that store
    HU + an offset the offset is detected, or given as ``hu_offset``, e.g. 1024), or none: 300 HU for DICOM and for
    stacks detected as HU + an offset, Otsu's level for other image stacks (``engine.level``). ``spacing`` is
    [z, y, x] mm; one whose order looks swapped is accepted and warned about in report.json's ``warnings``.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    iso: float | None = Field(
        default=None, ge=-FLOAT32_MAX, le=FLOAT32_MAX, description="iso level in the scan's units"
    )
    preset: Literal["bone", "compact-bone", "spongy-bone"] | None = Field(default=None, description="HU preset")
    hu_offset: float | None = Field(
        default=None, ge=-FLOAT32_MAX, le=FLOAT32_MAX, description="the stack stores HU + this offset (for preset)"
    )
    spacing: list[float] | None = Field(
        default=None,
        min_length=3,
        max_length=3,
        description=f"voxel size [z, y, x] in mm, each in [{SPACING_MM_MIN:g}, {SPACING_MM_MAX:g}]; image stacks "
        "need it unless their TIFF tags carry it",
    )
    zarr_level: StrictInt | StrictStr | None = Field(
        default=None,
        description="an OME-Zarr upload's resolution level: its index (0, the default: full resolution) or its path "
        "(as in the image's multiscales); refused for an upload of another kind",
    )
    reduction: float | None = Field(
        default=None, gt=0, le=1, description=f"fraction of faces kept (default {_DECIMATE.reduction:g})"
    )
    max_triangles: int | None = Field(
        default=None, ge=4, le=INT32_MAX, description="decimate to at most this many instead"
    )
    iterations: int = Field(
        default=_SMOOTH.iterations, ge=1, le=200, description="surface-preserving Laplacian iterations"
    )
    angle: float = Field(default=_SMOOTH.angle_deg, gt=0, lt=90, description="smoothing threshold angle, degrees")
    min_island_mm3: float | None = Field(
        default=None, ge=0, le=FLOAT32_MAX, description="drop pieces smaller than this volume (mm³)"
    )
    keep_largest: int | None = Field(default=None, ge=1, le=INT32_MAX, description="keep only the N largest pieces")
    orient: OrientJobParams = Field(default_factory=OrientJobParams, description="how an image stack lies")
    preprocess: PreprocessJobParams | None = Field(default=None, description="slice preprocessing (default off)")
    body: BodyJobParams | None = Field(
        default_factory=BodyJobParams, description="bone inside the body outline only (HU data); null: off"
    )
    islands: IslandJobParams | None = Field(
        default_factory=IslandJobParams, description="speck removal; null: keep pieces of any size"
    )
    defect: DefectJobParams | None = Field(
        default=None, description="the one-sided defect and its mirrored fill template (default off; {} turns it on)"
    )
    labels: bool | None = Field(
        default=None,
        description="true: the upload is a label map (an integer NIfTI, NRRD/.seg.nrrd, or a zip of one, or of a "
        "DICOM SEG with its CT series): one model per label. Label maps are found by their content without it",
    )
    pieces: int | None = Field(
        default=None, ge=1, le=1000, description="keep the N largest bone pieces of a CT as separately named parts"
    )
    roi: RoiJobParams | None = Field(default=None, description="crop to this box before anything runs")
    segments: (
        list[Annotated[int, Field(ge=1, le=65535)] | Annotated[str, Field(min_length=1, max_length=64)]] | None
    ) = Field(
        default=None,
        min_length=1,
        max_length=1000,
        description="a label job: only these segments (numbers or names), each its own model (and, from the PACS, "
        "its own Encapsulated STL)",
    )
    phone_max_triangles: int = Field(
        default=_EXPORT.phone_max_triangles, ge=100, le=2_000_000, description="phone.glb budget"
    )
    ar_max_triangles: int = Field(default=_EXPORT.ar_max_triangles, ge=100, le=2_000_000, description="ar.glb budget")

    @field_validator("spacing")
    @classmethod
    def _plausible(cls, value: list[float] | None) -> list[float] | None:
        if value is not None:
            check_spacing_zyx_mm(value)  # the engine's own range: the CLI refuses the same
        return value

    @model_validator(mode="after")
    def _consistent(self) -> JobParams:
        if self.iso is not None and self.preset is not None:
            raise ValueError("give iso or preset, not both")
        self.job_spec()  # the engine's rules, stated once (engine.job.spec, engine.params): 422 naming the value
        return self

    def warnings(self) -> list[dict[str, Any]]:
        """What a person should check in these parameters, in the API's words: a ``spacing`` whose order looks
        swapped (``engine.params.spacing_order_warning``), with the likely [z, y, x]. The job's report carries the
        same warning (the engine checks the spacing it was given); each is ``{"code", "message", ...}``."""
        order = spacing_order_warning(self.spacing) if self.spacing is not None else None
        if order is None:
            return []
        likely = order["likely_zyx_mm"]
        fix = f'; if so, send "spacing": [{", ".join(f"{v:g}" for v in likely)}]' if likely else ""
        given = ", ".join(f"{v:g}" for v in self.spacing or ())
        return [{**order, "message": f'"spacing" [{given}]: {order["message"]}{fix} (the API\'s order is [z, y, x])'}]

    def record(self) -> dict[str, Any]:
        """The job record's form (JSON-able): what was given or defaulted, without unset options, but with the
        steps sent as null (dropping those would switch them back on when the worker reads the record)."""
        data = self.model_dump(mode="json", exclude_none=True)
        data.update({name: None for name in SWITCHES if getattr(self, name) is None})
        return data

    def job_spec(self) -> JobSpec:
        """The engine's job specification (``engine.job.JobSpec``) of these parameters: what a job leaves out keeps
        the engine's default (``ReconParams()``), speck removal and the body mask included. The rules for the
        decimation's target and speck removal are the engine's (``decimate_of``, ``islands_of``), as the CLI's.

        Raises:
            ValueError: the engine refuses a value (the API answers 422).
        """
        recon = ReconParams(
            preprocess=None if self.preprocess is None else PreprocessParams(**self.preprocess.model_dump()),
            iso=IsoParams(iso=self.iso, preset=self.preset, hu_offset=self.hu_offset),
            islands=islands_of(
                self.min_island_mm3,
                self.keep_largest,
                keep_specks=self.islands is None,
                min_volume_voxels=DEFAULT_SPECK_VOXELS if self.islands is None else self.islands.min_volume_voxels,
            ),
            decimate=decimate_of(self.reduction, self.max_triangles),
            smooth=SmoothParams(iterations=self.iterations, angle_deg=self.angle),
            export=ExportParams(phone_max_triangles=self.phone_max_triangles, ar_max_triangles=self.ar_max_triangles),
            orient=OrientParams(**self.orient.model_dump()),
            body=None if self.body is None else BodyMaskParams(outline_hu=self.body.outline_hu),
            defect=None if self.defect is None else self.defect.engine(),
        )
        inp = InputSpec(
            kind="labels" if self.labels else "auto",
            spacing_zyx_mm=None if self.spacing is None else tuple(self.spacing),  # type: ignore[arg-type]
            roi=None if self.roi is None else self.roi.engine(),
            pieces=None if self.pieces is None else PiecesParams(count=self.pieces),
            segments=None if self.segments is None else tuple(self.segments),
            zarr_level=self.zarr_level,
        )
        return JobSpec(recon=recon, input=inp)

    def engine_params(self) -> dict[str, Any]:
        """The job record's engine form (``JobSpec.to_dict``: ``recon``, ``spacing_zyx_mm``, ``input``, ``outputs``).

        Raises:
            ValueError: the engine refuses a value (the API answers 422).
        """
        return self.job_spec().to_dict()
