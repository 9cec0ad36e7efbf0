"""What a job is, validated once: ``JobSpec`` (the reconstruction's parameters, what the input is, the outputs
wanted), built by every edge (the API's request model, ``core.params.JobParams.job_spec``; the CLI's flags,
``engine.cli.args.job_spec``; a PACS routing rule) and handed, already checked, to ``engine.job.run_job``.

Each rule is stated here or in ``engine.params`` once: a decimation target (``decimate_of``), speck removal
(``islands_of``), the voxel size's range (``check_spacing_zyx_mm``; its order is warned about by
``spacing_order_warning``), the segments a label job keeps, and which inputs the defect is looked for on.

A spec round-trips through JSON (``to_dict`` / ``from_dict``): the job record keeps it, so the worker reads the
job as the API checked it. Importing this module never loads Warp.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from typing import Any

from engine.params import PiecesParams, ReconParams, RoiParams, check_spacing_zyx_mm

__all__ = ["INPUT_KINDS", "InputSpec", "JobSpec", "OutputSpec"]

INPUT_KINDS = ("auto", "scan", "labels")  # auto: a label map is found by its content, else a scan
SEGMENT_NAME_MAX = 64
SEGMENT_VALUE_MAX = 65535
SEGMENTS_MAX = 1000


def _segment(value: object) -> int | str:
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise ValueError(f"a segment is a number or a name, got {value!r}")
    if isinstance(value, int) and not 1 <= value <= SEGMENT_VALUE_MAX:
        raise ValueError(f"a segment number is 1..{SEGMENT_VALUE_MAX}, got {value}")
    if isinstance(value, str) and not 1 <= len(value) <= SEGMENT_NAME_MAX:
        raise ValueError(f"a segment name has 1..{SEGMENT_NAME_MAX} characters, got {value!r}")
    return value


ZARR_LEVEL_CHARS = re.compile(r"[A-Za-z0-9_.-]{1,64}")


def check_zarr_level(level: object) -> int | str:
    """An OME-Zarr level as given: an index (an int from 0) or a level's path (up to 64 letters, digits, ``_``,
    ``.`` and ``-``; digits that are no level's path are an index, as ``engine.io.omezarr`` reads them).

    Raises:
        ValueError: anything else, in words.
    """
    if isinstance(level, bool) or not isinstance(level, int | str):
        raise ValueError(f"zarr_level is a level's index (0: full resolution) or its path, not {level!r}")
    if isinstance(level, int):
        if level < 0:
            raise ValueError(f"zarr_level is a level's index from 0 (the full resolution), not {level}")
        return level
    if not ZARR_LEVEL_CHARS.fullmatch(level) or level in (".", ".."):
        raise ValueError(f"zarr_level {level!r} is no level's path (letters, digits, '_', '.', '-'; up to 64)")
    return level


@dataclass(frozen=True)
class InputSpec:
    """What the input is and how it is cut before meshing.

    Args:
        kind: ``"auto"`` (a label map is found by its content: ``engine.labels.uploads.find_label_upload``, else a
            scan), ``"labels"`` (it must be a label map) or ``"scan"`` (a scan, never read as labels).
        spacing_zyx_mm: the voxel size where the files lack it (z, y, x mm).
        roi: a box the scan or label map is cropped to first.
        pieces: a scan's N largest bone pieces, each its own part (a label job made from a scan).
        segments: a label job keeps only these segments (numbers or names), each its own model.
        zarr_level: an OME-Zarr input's resolution level: its index (0: the full resolution, the default) or its
            path (``engine.io.omezarr``); an input of another kind refuses it when loaded.
    """

    kind: str = "auto"
    spacing_zyx_mm: tuple[float, float, float] | None = None
    roi: RoiParams | None = None
    pieces: PiecesParams | None = None
    segments: tuple[int | str, ...] | None = None
    zarr_level: int | str | None = None

    def __post_init__(self) -> None:
        if self.kind not in INPUT_KINDS:
            raise ValueError(f"input kind must be one of {', '.join(INPUT_KINDS)}, got {self.kind!r}")
        if self.spacing_zyx_mm is not None:
            object.__setattr__(self, "spacing_zyx_mm", check_spacing_zyx_mm(self.spacing_zyx_mm))
        if self.pieces is not None and self.kind == "labels":
            raise ValueError("give pieces (a CT's bone pieces) or labels (a label map), not both")
        if self.segments is not None:
            segments = tuple(_segment(s) for s in self.segments)
            if not 1 <= len(segments) <= SEGMENTS_MAX:
                raise ValueError(f"segments lists 1..{SEGMENTS_MAX} segments, got {len(segments)}")
            object.__setattr__(self, "segments", segments)
        if self.zarr_level is not None:
            object.__setattr__(self, "zarr_level", check_zarr_level(self.zarr_level))

    @property
    def label_job(self) -> bool:
        """Whether the job is a label job for certain (a label map asked for, or a scan's pieces)."""
        return self.kind == "labels" or self.pieces is not None

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form."""
        return {
            "kind": self.kind,
            "spacing_zyx_mm": None if self.spacing_zyx_mm is None else list(self.spacing_zyx_mm),
            "roi": None if self.roi is None else {"box": [list(r) for r in self.roi.box], "units": self.roi.units},
            "pieces": None if self.pieces is None else dataclasses.asdict(self.pieces),
            "segments": None if self.segments is None else list(self.segments),
            "zarr_level": self.zarr_level,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> InputSpec:
        """Inverse of :meth:`to_dict`; unknown keys raise ValueError."""
        _known(data, cls, "input")
        roi = data.get("roi")
        if roi is not None:
            _known(roi, RoiParams, "roi")
            box = tuple(tuple(r) for r in roi["box"])
            roi = RoiParams(box, units=roi.get("units", "voxels"))  # type: ignore[arg-type]
        pieces = data.get("pieces")
        spacing = data.get("spacing_zyx_mm")
        segments = data.get("segments")
        return cls(
            kind=data.get("kind", "auto"),
            spacing_zyx_mm=None if spacing is None else tuple(spacing),
            roi=roi,
            pieces=None if pieces is None else PiecesParams(**_known(pieces, PiecesParams, "pieces")),
            segments=None if segments is None else tuple(segments),
            zarr_level=data.get("zarr_level"),
        )


@dataclass(frozen=True)
class OutputSpec:
    """The files wanted beyond the registry's defaults: ``label_stl_folder`` keeps a label job's
    ``labels/<name>.stl`` beside ``labels.zip`` (the CLI's layout; a job's outputs hold the zip only)."""

    label_stl_folder: bool = False

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class JobSpec:
    """One job: the reconstruction's parameters (``recon``: the defect included), the input (``input``) and the
    outputs (``outputs``), checked together when made.

    Raises:
        ValueError: a value or a combination no job can run (the API answers 422, the CLI exits 2).
    """

    recon: ReconParams = field(default_factory=ReconParams)
    input: InputSpec = field(default_factory=InputSpec)
    outputs: OutputSpec = field(default_factory=OutputSpec)

    def __post_init__(self) -> None:
        inp = self.input
        if self.recon.defect is not None and (inp.label_job or inp.segments):
            raise ValueError("the defect is found on a CT's model, not on pieces or labels: give one or the other")

    def to_dict(self) -> dict[str, Any]:
        """The job record's engine form: ``recon`` (``ReconParams.to_dict``), ``spacing_zyx_mm`` (as records have
        always kept it), ``input`` and ``outputs``."""
        inp = self.input.to_dict()
        return {"recon": self.recon.to_dict(), "spacing_zyx_mm": inp.pop("spacing_zyx_mm"), "input": inp,
                "outputs": self.outputs.to_dict()}  # fmt: skip

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> JobSpec:
        """Inverse of :meth:`to_dict` (a record without ``input``: a scan or label map found by content)."""
        _known(data, None, "job", names={"recon", "spacing_zyx_mm", "input", "outputs"})
        inp = {**(data.get("input") or {}), "spacing_zyx_mm": data.get("spacing_zyx_mm")}
        outputs = data.get("outputs") or {}
        return cls(
            recon=ReconParams.from_dict(data.get("recon") or {}),
            input=InputSpec.from_dict(inp),
            outputs=OutputSpec(**_known(outputs, OutputSpec, "outputs")),
        )


def _known(data: Any, kind: Any, what: str, names: set[str] | None = None) -> dict[str, Any]:
    """``data`` when it is an object with only ``kind``'s field names (or ``names``), else ValueError."""
    if not isinstance(data, dict):
        raise ValueError(f"Expected {what} to be an object, got {type(data).__name__}")
    names = names if names is not None else {f.name for f in dataclasses.fields(kind)}
    bad = set(data) - names
    if bad:
        raise ValueError(f"Unknown {what} parameters {sorted(bad)}; expected some of {sorted(names)}")
    return data
