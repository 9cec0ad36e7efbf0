"""The defect template's parameters (``DefectParams``): a frozen dataclass that round-trips through JSON, like
``engine.params``' (the pipeline's ``ReconParams`` will carry one as its ``defect`` entry). Importing this module
never loads Warp or numpy."""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass
from typing import Any

SIDES = ("left", "right")  # the patient's: +x of the LPS frame is the patient's left
# the implant is decimated (lightly) only above this many triangles
DEFAULT_MAX_FACES = 200_000
# a model made with its defect template is not re-oriented (engine.job.reorient, the API's orient route): the
# template's side (left/right), plane and measures in defect.json belong to the orientation they were found in
DEFECT_REORIENT = (
    "{job} has a defect template: its side, plane and measures were found in the orientation the scan was given, "
    "so it cannot be re-oriented; submit the scan again with the right orientation"
)


def _number(value: object) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(float(value))


@dataclass(frozen=True)
class DefectParams:
    """How the defect is found and its template made (``engine.defect.run``).

    Args:
        side: a hint: the side of the patient the defect is on, "left" or "right" (patient frame, LPS: the
            patient's left is +x); only defects on that side are kept. None: either side.
        point_lps_mm: a hint: a point in or next to the defect (x, y, z in the patient frame, mm); the defect
            component nearest to it is kept (within ``point_radius_mm``), and the symmetry plane is fitted without
            the bone around it and around its mirror image.
        point_radius_mm: how far from ``point_lps_mm`` the defect may lie, and how much bone around it the plane
            fit leaves out.
        min_volume_mm3: smallest defect reported, mm^3; smaller ones are "no defect" (``NoDefectError``). None:
            the default rule (``engine.defect.region.min_defect_volume``: a 15 mm wide plug of the skull's own
            shell thickness, and at least 0.1 % of the skull's volume).
        max_faces: the implant mesh is decimated (quadric edge collapse, topology kept) to this many triangles when
            it has more; None keeps every triangle.
    """

    side: str | None = None
    point_lps_mm: tuple[float, float, float] | None = None
    point_radius_mm: float = 40.0
    min_volume_mm3: float | None = None
    max_faces: int | None = DEFAULT_MAX_FACES

    def __post_init__(self) -> None:
        if self.side is not None and self.side not in SIDES:
            raise ValueError(f"side must be one of {list(SIDES)} or None, got {self.side!r}")
        if self.point_lps_mm is not None:
            p = tuple(self.point_lps_mm)
            if len(p) != 3 or not all(_number(v) for v in p):
                raise ValueError(f"point_lps_mm must be three finite numbers (x, y, z, mm), got {self.point_lps_mm!r}")
            object.__setattr__(self, "point_lps_mm", tuple(float(v) for v in p))
        if not _number(self.point_radius_mm) or not 0 < self.point_radius_mm <= 500:
            raise ValueError(f"point_radius_mm must be in (0, 500], got {self.point_radius_mm!r}")
        if self.min_volume_mm3 is not None and (not _number(self.min_volume_mm3) or self.min_volume_mm3 < 0):
            raise ValueError(f"min_volume_mm3 must be a number >= 0 or None, got {self.min_volume_mm3!r}")
        if self.max_faces is not None:
            ok = isinstance(self.max_faces, numbers.Integral) and not isinstance(self.max_faces, bool)
            if not ok or not 100 <= int(self.max_faces) <= 2**31 - 1:
                raise ValueError(f"max_faces must be an integer >= 100 or None, got {self.max_faces!r}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-able (tuples as lists)."""
        out = asdict(self)
        if self.point_lps_mm is not None:
            out["point_lps_mm"] = list(self.point_lps_mm)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> DefectParams:
        """Inverse of :meth:`to_dict`; unknown keys are refused (``ValueError``)."""
        data = dict(data or {})
        known = {"side", "point_lps_mm", "point_radius_mm", "min_volume_mm3", "max_faces"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown defect parameter(s): {', '.join(unknown)}")
        if data.get("point_lps_mm") is not None:
            data["point_lps_mm"] = tuple(data["point_lps_mm"])
        return cls(**data)
