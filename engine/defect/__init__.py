"""The defect itself (issue 31): the bone's symmetry plane, the bone that the mirror image has and the scan lacks,
and a watertight template of it to print (``implant.stl``) with its measures (``defect.json``).

* ``plane``: ``find_symmetry_plane`` (mirror-ICP constrained to reflections, robust to the defect);
* ``region``: the defect's voxels (mirror, shell rule, missing-not-moved, rim, size) on Warp kernels
  (``engine.defect.kernels``: the mirrored scan, the voxel rules, an exact distance transform), ``rim`` its fit;
* ``implant``: the template's surface (MC33, closed, patient frame);
* ``template``: ``run`` (plane + template: what the pipeline and ``bonemesh defect`` call), ``defect_template``,
  ``DefectResult`` (``to_json``) and ``write_defect``; ``params``: ``DefectParams``.

Refusals are ``InputError``s of ``engine.errors``: ``NoSymmetryError``, ``NoDefectError``, ``MidlineDefectError``.
The package imports no service, worker or core; public names load lazily (``engine._lazy``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.defect.params import DefectParams
    from engine.defect.plane import SymmetryPlane, find_symmetry_plane
    from engine.defect.template import DefectResult, defect_template, run, write_defect

__all__ = [
    "DefectParams",
    "DefectResult",
    "SymmetryPlane",
    "defect_template",
    "find_symmetry_plane",
    "run",
    "write_defect",
]
__getattr__, __dir__ = attach(
    __name__,
    {
        "DefectParams": ".params",
        "DefectResult": ".template",
        "SymmetryPlane": ".plane",
        "defect_template": ".template",
        "find_symmetry_plane": ".plane",
        "run": ".template",
        "write_defect": ".template",
    },
)
