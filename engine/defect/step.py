"""The defect as a step of a reconstruction (``ReconParams.defect``): ``find_defect`` runs ``engine.defect.run`` on
the scan at the model's own level and keeps its answer, a template or a refusal, for the files:

* ``implant.stl`` (the template, patient LPS mm, beside ``model.stl``) when one was found;
* ``defect.json``: the template's measures (``DefectResult.to_json``), or ``"found": false`` with the refusal's
  code and message (an intact bone, a defect across the midline, no symmetry to mirror): a clear answer, never a
  made-up implant; the bone's own model is delivered either way;
* the template as its own coloured node in the glTF files that take parts (``engine.export.files``), at a share of
  each file's triangle budget.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from engine.defect.params import DefectParams
from engine.defect.template import FORMAT, DefectResult, defect_json, implant_stl
from engine.errors import MidlineDefectError, NoDefectError, NoSymmetryError
from engine.export.files import DEFECT_JSON, IMPLANT_STL

# the refusals that are answers (the reconstruction still delivers its model), by their code in defect.json
REFUSALS = ((NoDefectError, "no_defect"), (MidlineDefectError, "midline_defect"), (NoSymmetryError, "no_symmetry"))
TEMPLATE_NODE = "defect template"
# the template's share of a viewing copy's triangle budget (it is small beside the skull), and its floor
VIEW_SHARE, VIEW_MIN_FACES = 0.1, 2_000


@dataclass
class DefectOutcome:
    """What the defect step found: a ``result`` (the template) or a ``refusal`` (``{"code", "message"}``), and what
    it was measured on (``measured_on``: ``measured_on()``, written into defect.json and the report)."""

    result: DefectResult | None
    refusal: dict[str, str] | None
    seconds: float
    measured_on: dict[str, Any] | None = None

    def summary(self) -> dict[str, Any]:
        """``report.json``'s ``defect`` block: found or not, the refusal, or the template's size and plane."""
        on = {} if self.measured_on is None else {"measured_on": self.measured_on}
        if self.result is None:
            return {"found": False, **(self.refusal or {}), **on, "seconds": round(self.seconds, 4)}
        info = self.result.to_json()
        keep = ("side", "volume_mm3", "area_mm2", "slices", "rim")
        return {
            "found": True,
            **{k: info["defect"][k] for k in keep},
            "plane_residual_mm": info["plane"]["residual_mm"],
            "implant_faces": info["implant"]["faces"],
            **({"warnings": info["warnings"]} if info["warnings"] else {}),
            **on,
            "seconds": round(self.seconds, 4),
        }

    def files(self) -> dict[str, bytes]:
        """The step's files by name: ``defect.json`` always, ``implant.stl`` with a template."""
        on = {} if self.measured_on is None else {"measured_on": self.measured_on}
        if self.result is None:
            return {DEFECT_JSON: defect_json({"format": FORMAT, "found": False, **(self.refusal or {}), **on})}
        return {DEFECT_JSON: defect_json({**self.result.to_json(), **on}), IMPLANT_STL: implant_stl(self.result)}

    def part(self, centre_zyx_mm: Any, max_faces: int | None, device: Any = "auto") -> Any:
        """The template as a glTF ``Part`` centred as the model's glTF files are (``centre_zyx_mm`` subtracted),
        decimated (topology kept) to ``max_faces`` when given and smaller than it; None without a template."""
        from engine.export.glb import Part

        if self.result is None:
            return None
        verts, faces = self.result.mesh.vertices, self.result.mesh.faces
        if max_faces is not None and len(faces) > max_faces:
            from engine.decimation import decimate_mesh

            verts, faces, _ = decimate_mesh(verts, faces, max_triangles=max_faces, device=device)
        return Part(TEMPLATE_NODE, verts, faces).moved([-float(c) for c in centre_zyx_mm])


def view_faces(budget: int) -> int:
    """The template's triangles in a viewing copy of ``budget`` triangles."""
    return max(VIEW_MIN_FACES, int(budget * VIEW_SHARE))


def measured_on(orient: Any, level: dict[str, Any], body: dict[str, Any] | None) -> dict[str, Any]:
    """What a defect was measured on, for defect.json: the stack's orientation (``OrientParams``: a DICOM series is
    placed by its headers), the level (``LevelChoice.report``) and the scan it was found in (bone inside the body
    outline, or the whole scan)."""
    import dataclasses

    applied = bool(body and body.get("applied"))
    return {
        "orientation": dataclasses.asdict(orient) if orient is not None else None,
        "level": level,
        "scan": "bone inside the body outline" if applied else "the whole scan",
    }


def find_defect(
    volume: Any, params: DefectParams, level: float, device: Any, orient: Any, on: dict[str, Any] | None = None
) -> DefectOutcome:
    """``engine.defect.run`` at the model's level; its refusals (``REFUSALS``) become the outcome's ``refusal``.

    Raises:
        EmptySurfaceError and other errors of ``run`` that are not answers about the defect.
    """
    from engine.defect.template import run

    t0 = time.perf_counter()
    try:
        result = run(volume, params, level, device, orient=orient)
    except tuple(kind for kind, _ in REFUSALS) as exc:
        code = next(code for kind, code in REFUSALS if isinstance(exc, kind))
        return DefectOutcome(None, {"code": code, "message": str(exc)}, time.perf_counter() - t0, on)
    return DefectOutcome(result, None, time.perf_counter() - t0, on)
