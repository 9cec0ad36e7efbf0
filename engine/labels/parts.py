"""A model per label as named, coloured parts in the patient frame (``label_models``), and their files
(``write_label_stls``: ``labels/<name>.stl`` and ``labels.zip``).

A part is what a multi-node ``model.glb`` takes: a name, an sRGB colour (0-1), vertices (LPS x, y, z in mm) and
outward faces (in that vertex order), with its stats (volume mm3, area mm2, faces, watertight).
"""

from __future__ import annotations

import os
import re
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.io.labelmaps import LabelVolume
from engine.params import OrientParams, ReconParams
from engine.types import Mesh

__all__ = ["LabelModels", "LabelPart", "file_names", "label_models", "write_label_stls"]


@dataclass
class LabelPart:
    """One label's watertight model: ``vertices_xyz`` (V, 3) float32 LPS mm, ``faces`` (F, 3) int32 outward."""

    name: str
    value: int
    color: tuple[float, float, float]
    vertices_xyz: npt.NDArray[np.float32]
    faces: npt.NDArray[np.int32]
    stats: dict[str, Any] = field(default_factory=dict)

    def mesh(self) -> Mesh:
        """The part in the engine's ``Mesh`` layout ((z, y, x) order) in the patient frame."""
        return Mesh(np.ascontiguousarray(self.vertices_xyz[:, ::-1]), self.faces)


@dataclass
class LabelModels:
    """The parts, in the label map's segment order, and a JSON-able report (``labels``: one entry per part)."""

    parts: list[LabelPart]
    report: dict[str, Any]


def _split(vertices: np.ndarray, faces: np.ndarray, slot: np.ndarray, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The joined mesh split by label slot (a label's vertices are its own): per slot (vertices, faces), in one
    sort of the vertices and one of the faces (as int16 where the slots fit: numpy's stable sort is then a radix
    sort, linear in the mesh)."""
    if n < 1 << 15:
        slot = slot.astype(np.int16, copy=False)
    fslot = slot[faces[:, 0]] if len(faces) else np.zeros(0, slot.dtype)
    vorder = np.argsort(slot, kind="stable")
    forder = np.argsort(fslot, kind="stable")
    new_index = np.empty(len(slot), dtype=np.int64)
    new_index[vorder] = np.arange(len(slot))
    vb = np.searchsorted(slot[vorder], np.arange(n + 1))
    fb = np.searchsorted(fslot[forder], np.arange(n + 1))
    v_sorted, f_sorted = vertices[vorder], new_index[faces[forder]]
    return [(v_sorted[vb[s] : vb[s + 1]], (f_sorted[fb[s] : fb[s + 1]] - vb[s]).astype(np.int32)) for s in range(n)]


def _measures(vertices: np.ndarray, faces: np.ndarray, slot: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Volume (mm3) and area (mm2) per label slot, with one cross product per face (``a . (b x c) =
    a . ((b - a) x (c - a))``, so the area's normal gives the volume too), in chunks of faces on the host's cores
    (numpy releases the GIL in these loops: the 8 M faces of 100 labels took 1.1 s in one thread on the H100 host)."""
    from concurrent.futures import ThreadPoolExecutor

    def chunk(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        f = faces[lo:hi]
        a = vertices[f[:, 0], ::-1].astype(np.float64)
        normal = np.cross(vertices[f[:, 1], ::-1].astype(np.float64) - a, vertices[f[:, 2], ::-1] - a)
        fslot = slot[f[:, 0]]
        volume = np.bincount(fslot, np.einsum("ij,ij->i", a, normal) / 6.0, minlength=n)
        area = np.bincount(fslot, 0.5 * np.sqrt(np.einsum("ij,ij->i", normal, normal)), minlength=n)
        return volume, area

    step = max(1 << 18, -(-len(faces) // (os.cpu_count() or 1)))
    bounds = [(lo, min(lo + step, len(faces))) for lo in range(0, len(faces), step)] or [(0, 0)]
    with ThreadPoolExecutor(min(len(bounds), os.cpu_count() or 1)) as pool:
        parts = list(pool.map(lambda b: chunk(*b), bounds))
    return sum(p[0] for p in parts), sum(p[1] for p in parts)  # in chunk order: the same sums every run


def voxel_counts(labels: np.ndarray, chunk: int = 1 << 23) -> np.ndarray | None:
    """Voxels per label value (uint8/uint16 maps), counted a chunk at a time on the host's cores (a whole-map
    ``bincount`` first makes an int64 copy of it: 800 MB and 1.8 s for a 512x512x400 map here); None for wider
    types."""
    from concurrent.futures import ThreadPoolExecutor

    if labels.dtype.itemsize > 2:
        return None
    flat = labels.reshape(-1)
    counts = np.zeros(1 << (8 * labels.dtype.itemsize), np.int64)
    with ThreadPoolExecutor(os.cpu_count() or 1) as pool:
        for part in pool.map(np.bincount, (flat[i : i + chunk] for i in range(0, flat.size, chunk))):
            counts[: len(part)] += part
    return counts


def _closed(f: np.ndarray, n_vertices: int, joined_closed: bool) -> bool:
    """Watertight: every label is when the joined mesh is (labels share no vertex, so no edge); else checked."""
    if joined_closed or len(f) == 0:
        return joined_closed and len(f) > 0
    from engine.surface.meshcheck import edge_report

    edges = edge_report(f, n_vertices)
    return bool(edges["boundary_edges"] == 0 and edges["nonmanifold_edges"] == 0)


def label_models(
    lv: LabelVolume,
    params: ReconParams | None = None,
    *,
    device: Any = "auto",
    orient: OrientParams | None = None,
) -> LabelModels:
    """Every segment of ``lv`` meshed in one batch (``engine.labels.extract.mesh_labels``) and placed in the patient
    frame (``engine.orient.patient_frame``: the map's own geometry, or ``orient`` for a grid without one).
    Segments that overlap (a DICOM SEG's segments are independent masks: ``LabelVolume.masks``) are meshed in as
    few batches as keep each one whole (``LabelVolume.layers``), the parts in the map's segment order.

    Raises:
        EmptyLabelError: a segment has no voxels; StageError: the device work failed otherwise.
    """
    layers = lv.layers()  # segments that overlap (a SEG's independent masks) are meshed in layers, each whole
    names = dict(zip((s.value for s in lv.segments), file_names(lv), strict=True))
    if len(layers) == 1:
        return _layer_models(lv, params, device, orient, names)
    done = [_layer_models(layer, params, device, orient, names, empty_ok=True) for layer in layers]
    order = {s.value: i for i, s in enumerate(lv.segments)}
    pairs = sorted(
        ((part, row) for m in done for part, row in zip(m.parts, m.report["labels"], strict=True)),
        key=lambda pr: order[pr[0].value],
    )
    if not pairs:
        from engine.errors import EmptySurfaceError

        raise EmptySurfaceError("no label gives a surface (each is thinner than a voxel after smoothing)")
    report = {
        **done[0].report,
        "labels": [row for _, row in pairs],
        "labels_without_surface": [d for m in done for d in m.report["labels_without_surface"]],
        "labels_mesh": {**done[0].report["labels_mesh"], "layers": len(layers)},
        "source": lv.source,
    }
    return LabelModels([part for part, _ in pairs], report)


def _layer_models(
    lv: LabelVolume,
    params: ReconParams | None,
    device: Any,
    orient: OrientParams | None,
    names: dict[int, str],
    empty_ok: bool = False,
) -> LabelModels:
    """The segments of one layer (no two overlap) meshed in one batch and placed; ``names``: each segment's file
    name (unique over the whole map)."""
    from engine.labels.extract import mesh_labels
    from engine.orient import patient_frame, to_patient

    params = params or ReconParams()
    values = [s.value for s in lv.segments]
    joined = mesh_labels(lv.labels, values, lv.spacing_zyx_mm, params, device=device)
    frame = patient_frame(lv.as_volume(), orient or params.orient)
    voxel_mm3 = float(np.prod(lv.spacing_zyx_mm))
    counts = voxel_counts(lv.labels)
    parts, rows, dropped = [], [], []
    n = len(values)
    volumes, areas = _measures(joined.vertices, joined.faces, joined.slot, n)
    closed = bool(joined.info.get("watertight", False))
    pieces = _split(joined.vertices, joined.faces, joined.slot, n)
    for i, (seg, (v, f)) in enumerate(zip(lv.segments, pieces, strict=True)):
        name = names[seg.value]
        if len(f) == 0:  # voxels, but thinner than the smoothed level keeps (one voxel wide): no model
            dropped.append(seg.to_dict())
            continue
        stats = {
            "faces": len(f),
            "vertices": len(v),
            "volume_mm3": float(volumes[i]),
            "area_mm2": float(areas[i]),
            "watertight": _closed(f, len(v), closed),
        }
        if counts is not None:
            stats["voxels"] = int(counts[seg.value])
            stats["voxel_volume_mm3"] = int(counts[seg.value]) * voxel_mm3
        placed = to_patient(Mesh(v.astype(np.float32), f), frame)
        xyz = np.ascontiguousarray(placed.vertices[:, ::-1])
        parts.append(LabelPart(seg.name, seg.value, seg.color, xyz, placed.faces, stats))
        rows.append({**seg.to_dict(), "file": f"labels/{name}.stl", **stats})
    if not parts and not empty_ok:
        from engine.errors import EmptySurfaceError

        raise EmptySurfaceError("no label gives a surface (each is thinner than a voxel after smoothing)")
    report = {
        "labels": rows,
        "labels_without_surface": dropped,
        "frame": frame.to_dict(),
        "labels_mesh": joined.info,
        "source": lv.source,
    }
    return LabelModels(parts, report)


def file_names(lv: LabelVolume) -> list[str]:
    """A file-safe, unique name per segment (``label_<value>`` when its name has no usable character)."""
    names: list[str] = []
    for s in lv.segments:
        base = re.sub(r"[^A-Za-z0-9._-]+", "_", s.name).strip("._") or f"label_{s.value}"
        name, n = base, 2
        while name.lower() in (m.lower() for m in names):
            name, n = f"{base}_{n}", n + 1
        names.append(name)
    return names


def write_label_stls(models: LabelModels, folder: str | Path) -> dict[str, Path]:
    """``labels/<name>.stl`` per part (binary, LPS mm) and ``labels.zip`` of them in ``folder``; each written to a
    temporary name first and renamed, so no partial file is left. Returns {relative name: path}."""
    from engine.export.stl import to_stl

    root = Path(folder)
    (root / "labels").mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    for row, part in zip(models.report["labels"], models.parts, strict=True):
        data = to_stl(part.mesh().vertices, part.faces, header=f"bonemesh label {part.name}, patient LPS frame, mm")
        paths[row["file"]] = _atomic_write(root / row["file"], data)
    fd, tmp = tempfile.mkstemp(dir=root, prefix=".labels.zip.", suffix=".part")
    os.close(fd)
    try:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
            for rel, path in paths.items():  # a fixed date and mode: the same parts give the same archive's bytes
                info = zipfile.ZipInfo(rel, date_time=(1980, 1, 1, 0, 0, 0))
                info.external_attr = 0o100644 << 16
                zf.writestr(info, path.read_bytes(), compress_type=zipfile.ZIP_DEFLATED)
        os.replace(tmp, root / "labels.zip")
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    paths["labels.zip"] = root / "labels.zip"
    return paths


def _atomic_write(path: Path, data: bytes) -> Path:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
