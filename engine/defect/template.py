"""The defect template: ``run`` (plane, then template) and ``defect_template`` (a given plane), their result
``DefectResult`` (``to_json``: ``defect.json``) and ``write_defect`` (``implant.stl`` and ``defect.json``)."""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.defect.grid import Grid, bone_and_skull
from engine.defect.params import DefectParams
from engine.defect.plane import SymmetryPlane, find_symmetry_plane, skull_masks
from engine.defect.region import Piece, Region, find_region
from engine.export.files import DEFECT_JSON, IMPLANT_STL
from engine.types import Mesh, Volume

FORMAT = "bonemesh defect 1"
PATIENT_FRAME = "LPS mm (DICOM patient frame: +x patient's left, +y posterior, +z superior)"


@dataclass
class DefectResult:
    """A defect and its template.

    ``mesh``: the implant (watertight, patient frame, mm; ``Mesh`` layout: ``vertices[:, ::-1]`` are LPS);
    ``mask``: the template's voxels on the crop whose first voxel is ``mask_lo`` (``full_mask`` gives it on the
    whole grid); ``pieces``: every candidate the rules looked at, with its verdict (``engine.defect.region``).
    """

    plane: SymmetryPlane
    mesh: Mesh
    mask: npt.NDArray[np.bool_]
    mask_lo: tuple[int, int, int]
    shape: tuple[int, int, int]
    voxel_mm3: float
    level: float
    units: str
    tissue: float
    shell_mm: float
    min_volume_mm3: float
    pieces: list[Piece]
    mesh_stats: dict[str, Any]
    implant_info: dict[str, Any]
    placed_by: str
    spacing_zyx: tuple[float, float, float]
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def kept(self) -> list[Piece]:
        return [p for p in self.pieces if p.kept]

    @property
    def volume_mm3(self) -> float:
        """The implant's volume (its closed surface)."""
        return float(self.mesh_stats["volume_mm3"])

    @property
    def area_mm2(self) -> float:
        return float(self.mesh_stats["area_mm2"])

    @property
    def side(self) -> str:
        left = sum(p.volume_mm3 for p in self.kept if p.side_mm[1] > 0)
        return "left" if left >= 0.5 * sum(p.volume_mm3 for p in self.kept) else "right"

    def rim(self) -> dict[str, float]:
        """The rim over the kept pieces (weighted by their perimeters): gap in mm and voxels, contact share."""
        rims = [p.rim for p in self.kept if p.rim is not None and p.rim.samples]
        w = np.array([r.samples for r in rims], dtype=np.float64)
        if not len(rims):
            return {"gap_mm": float("nan"), "gap_voxels": float("nan"), "contact_share": float("nan")}
        return {
            "gap_mm": float(np.average([r.gap_mm for r in rims], weights=w)),
            "gap_voxels": float(np.average([r.gap_voxels for r in rims], weights=w)),
            "contact_share": float(np.average([r.contact for r in rims], weights=w)),
        }

    @property
    def warnings(self) -> list[dict[str, Any]]:
        """What the template's user must know (``{"code", "message", ...}``): a hole that goes on past the midline
        plane by less than the tolerance (``region.midline_warning``, code ``past_midline``)."""
        from engine.defect.region import midline_warning

        return [w for w in (midline_warning(p) for p in self.kept) if w]

    def full_mask(self) -> npt.NDArray[np.bool_]:
        """The template's voxels on the whole grid."""
        out = np.zeros(self.shape, dtype=bool)
        z, y, x = self.mask_lo
        out[z : z + self.mask.shape[0], y : y + self.mask.shape[1], x : x + self.mask.shape[2]] = self.mask
        return out

    def to_json(self) -> dict[str, Any]:
        """``defect.json``: JSON-able, every length in mm and every position in the patient frame (LPS)."""
        xyz = self.mesh.vertices[:, ::-1].astype(np.float64)
        lo, hi = xyz.min(axis=0), xyz.max(axis=0)
        idx = np.argwhere(self.mask) + np.asarray(self.mask_lo)
        rim = self.rim()
        voxel_gap = rim["gap_voxels"]
        past = [p.across.past_mm for p in self.kept if p.across is not None]
        return {
            "format": FORMAT,
            "found": True,
            "frame": PATIENT_FRAME,
            "placed_by": self.placed_by,
            "level": {"value": self.level, "units": self.units},
            "plane": self.plane.to_dict(),
            "defect": {
                "side": self.side,
                "volume_mm3": round(self.volume_mm3, 2),
                "voxel_volume_mm3": round(float(self.mask.sum()) * self.voxel_mm3, 2),
                "area_mm2": round(self.area_mm2, 2),
                "extent_lps_mm": {
                    "min": [round(float(v), 2) for v in lo],
                    "max": [round(float(v), 2) for v in hi],
                    "size": [round(float(v), 2) for v in hi - lo],
                },
                "centroid_lps_mm": [round(float(v), 2) for v in xyz.mean(axis=0)],
                "slices": [int(idx[:, 0].min()), int(idx[:, 0].max())],
                "pieces": sum(1 for _ in self.kept),
                "rim": {
                    "gap_mm": round(rim["gap_mm"], 4),
                    "gap_voxels": round(voxel_gap, 4),
                    "contact_share": round(rim["contact_share"], 4),
                },
                "shell_thickness_mm": round(self.shell_mm, 3),
                "tissue_level": round(self.tissue, 2),
                "min_volume_mm3": round(self.min_volume_mm3, 2),
                "past_midline_mm": round(max(past), 2) if past else None,
            },
            "warnings": self.warnings,
            "implant": {
                "file": IMPLANT_STL,
                "faces": int(self.mesh_stats["n_faces"]),
                "vertices": int(self.mesh_stats["n_vertices"]),
                "watertight": bool(self.mesh_stats["watertight"]),
                "manifold": bool(self.mesh_stats["manifold"]),
                "components": int(self.mesh_stats["components"]),
                **self.implant_info,
            },
            "candidates": [p.to_dict() for p in self.pieces],
            "seconds": {k: round(v, 4) for k, v in self.seconds.items()},
        }


def defect_template(
    volume: Volume,
    level: float,
    plane: SymmetryPlane,
    *,
    params: DefectParams | None = None,
    device: Any = "auto",
    orient: Any = None,
    bone: npt.NDArray[np.bool_] | None = None,
    skull: npt.NDArray[np.bool_] | None = None,
) -> DefectResult:
    """The defect across ``plane`` and its implant (``engine.defect.region``, ``engine.defect.implant``).

    Args:
        volume: the scan; level: the bone level in its units; plane: ``find_symmetry_plane``'s.
        params: hints and limits (default ``DefectParams()``).
        device: "auto", "cpu", "cuda[:N]", "opencl[:N]" or a ``Backend`` (the voxel rules and MC33 run there).
        orient: ``OrientParams`` placing an image stack (default: the stack convention).
        bone, skull: the masks when the caller has them (``engine.defect.grid.bone_and_skull``).

    Raises:
        NoDefectError: no one-sided defect (an intact bone, or one below ``min_volume_mm3``).
        MidlineDefectError: the defect crosses the symmetry plane.
        EmptySurfaceError: no bone at the level.
    """
    from engine.defect.implant import implant_mesh
    from engine.device import resolve_backend
    from engine.surface import mesh_stats

    params = params or DefectParams()
    dev = resolve_backend(device)  # the voxel rules and MC33 run on its backend (Warp or OpenCL)
    grid = Grid.of(volume, orient)
    t0 = time.perf_counter()
    if bone is None or skull is None:
        bone, skull = bone_and_skull(volume.data, level)
    seconds = {"masks": time.perf_counter() - t0}
    t1 = time.perf_counter()
    region: Region = find_region(volume.data, level, plane, grid, bone, skull, params, dev)
    seconds["region"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    mesh, info = implant_mesh(
        region.mask, region.lo, region.data, region.mirrored, level, level - region.tissue, grid,
        device=dev, max_faces=params.max_faces,
    )  # fmt: skip
    seconds["implant"] = time.perf_counter() - t2
    stats = mesh_stats(mesh.vertices, mesh.faces)
    return DefectResult(
        plane=plane,
        mesh=mesh,
        mask=region.mask,
        mask_lo=tuple(int(v) for v in region.lo),  # type: ignore[arg-type]
        shape=grid.shape,
        voxel_mm3=grid.voxel_mm3,
        level=float(level),
        units=volume.units,
        tissue=region.tissue,
        shell_mm=region.shell_mm,
        min_volume_mm3=region.min_volume_mm3,
        pieces=region.pieces,
        mesh_stats=stats,
        implant_info=info,
        placed_by=grid.placed_by,
        spacing_zyx=grid.spacing_zyx,
        seconds={**seconds, **{f"region_{k}": v for k, v in region.seconds.items()}},
    )


def run(
    volume: Volume,
    params: DefectParams | None = None,
    level: float | None = None,
    device: Any = "auto",
    *,
    orient: Any = None,
) -> DefectResult:
    """The symmetry plane, then the defect template: what the pipeline and the CLI call.

    Args:
        volume: the scan.
        params: hints and limits (default ``DefectParams()``).
        level: the bone level in the volume's units (``engine.level.resolve_level``'s value); required.
        device: where the voxel rules and MC33 run, and (on a GPU) the skull's masks and the plane's queries.
        orient: ``OrientParams`` placing an image stack in the patient frame.

    Raises:
        NoSymmetryError, NoDefectError, MidlineDefectError, EmptySurfaceError (all ``InputError``).
    """
    if level is None:
        raise ValueError("run needs the bone level (engine.level.resolve_level)")
    params = params or DefectParams()
    t0 = time.perf_counter()
    bone, skull = skull_masks(volume.data, level, device)  # on the device where it is not the host's CPU
    masks = time.perf_counter() - t0
    plane = find_symmetry_plane(volume, level, params, orient=orient, skull=skull, device=device)
    result = defect_template(volume, level, plane, params=params, device=device, orient=orient, bone=bone, skull=skull)
    result.seconds = {
        "masks": masks,
        "plane": plane.seconds,
        **{k: v for k, v in result.seconds.items() if k != "masks"},
    }
    result.seconds["total"] = time.perf_counter() - t0
    return result


def write_defect(result: DefectResult, out_dir: str | Path) -> dict[str, Path]:
    """Write ``implant.stl`` (binary, patient frame, mm) and ``defect.json`` into ``out_dir``, each atomically
    (written beside, then renamed). Returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {IMPLANT_STL: out / IMPLANT_STL, DEFECT_JSON: out / DEFECT_JSON}
    _atomic(paths[IMPLANT_STL], implant_stl(result))
    _atomic(paths[DEFECT_JSON], defect_json(result.to_json()))
    return paths


def implant_stl(result: DefectResult) -> bytes:
    """``implant.stl``'s bytes: binary STL, patient frame, mm."""
    from engine.export.stl import to_stl

    return to_stl(result.mesh.vertices, result.mesh.faces, header="bonemesh defect template, patient LPS frame, mm")


def defect_json(doc: dict[str, Any]) -> bytes:
    """``defect.json``'s bytes: the document indented, NaN and infinities as null."""
    return (json.dumps(finite(doc), indent=2, allow_nan=False, default=_json_default) + "\n").encode()


def finite(obj: Any) -> Any:
    """The JSON with every infinite or NaN number as null (no gap measured)."""
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if isinstance(obj, float | np.floating) and not np.isfinite(obj):
        return None
    return obj


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"{type(obj).__name__} is not JSON-able")


def _atomic(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, 0o644)  # as an ordinary file (mkstemp makes it private)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
