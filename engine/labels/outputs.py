"""The files of a label job (a segmentation, or a CT's bone ``pieces``): ``write_label_outputs``.

* ``model.glb``: one node per label, named by its segment and coloured with its colour (``engine.export.glb.Part``;
  the first label is the document's own mesh, its material recoloured), all centred on the union's bounding box
  (``report["frame"]["gltf_centre_lps_mm"]``), in the glTF frame of every other model;
* ``phone.glb`` (Draco) and ``ar.glb``: the same nodes, each label decimated (topology kept) to its area share of
  the copy's triangle budget (``engine.labels.extract.share_by_area``; the AR copy from the phone copy);
* ``preview.png``: the phone copy's labels together;
* ``labels.zip``: ``labels/<name>.stl`` per label (binary, watertight, patient LPS mm; ``write_label_stls``, the
  files the CLI writes) and, with ``stl_folder``, the ``labels/`` folder itself;
* ``report.json``: each label's value, name, colour, volume, area and faces (``label_models``' report), the
  total (``mesh.n_faces``: model.glb's and labels.zip's triangles) and each file's bytes and faces (``exports``).

Every file is written into a temporary folder inside ``outdir`` and moved in only when all are complete.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from engine.export.files import LABELS_ZIP, MODEL_GLB, REPORT_JSON, engine_files, move_files
from engine.labels.parts import LabelModels, LabelPart, write_label_stls
from engine.params import ReconParams

__all__ = ["copy_parts", "write_label_outputs"]


def _glb_part(part: LabelPart, vertices_zyx: Any, faces: Any, centre_zyx: np.ndarray) -> Any:
    from engine.export.glb import Part

    verts = np.asarray(vertices_zyx, np.float64) - centre_zyx
    return Part(part.name, verts, np.asarray(faces, np.int32), (*part.color, 1.0))


def copy_parts(
    models: LabelModels, centre_zyx: np.ndarray, budget: int | None, device: Any = "auto"
) -> tuple[list[Any], list[dict[str, Any]]]:
    """Each label as a glTF ``Part`` centred on ``centre_zyx`` (mm), decimated to its area share of ``budget``
    triangles (None: whole), and how each was made."""
    from engine.labels.extract import share_by_area

    areas = np.array([p.stats.get("area_mm2", 0.0) for p in models.parts])
    shares = share_by_area(areas, budget) if budget is not None else [None] * len(models.parts)
    parts, infos = [], []
    for part, share in zip(models.parts, shares, strict=True):
        verts, faces = part.mesh().vertices, part.faces
        if share is not None and len(faces) > share:
            from engine.decimation import decimate_mesh

            verts, faces, _ = decimate_mesh(verts, faces, max_triangles=int(share), device=device)
        parts.append(_glb_part(part, verts, faces, centre_zyx))
        infos.append({"name": part.name, "share": None if share is None else int(share), "faces": len(faces)})
    return parts, infos


def _first_coloured(glb: bytes, first: Any) -> bytes:
    """A GLB whose own mesh is the first label: its material becomes that label's (name and colour)."""
    from engine.export.glb import pack_glb, part_material

    n = int.from_bytes(glb[12:16], "little")
    document = json.loads(glb[20 : 20 + n])
    binary = b""
    if len(glb) > 20 + n:
        length = int.from_bytes(glb[20 + n : 24 + n], "little")
        binary = glb[28 + n : 28 + n + length]
    document["materials"][0] = part_material(first)
    document["scenes"][0]["name"] = "labels"
    return pack_glb(document, binary)


def _glb(parts: list[Any], draco: bool) -> bytes:
    """A GLB of the parts: the first one the document's mesh, the others beside it."""
    from engine.export.draco import to_draco_glb
    from engine.export.glb import to_glb

    first, rest = parts[0], parts[1:]
    encode = to_draco_glb if draco else to_glb
    data = encode(first.vertices_zyx_mm, first.faces, name=first.name, parts=rest)
    return _first_coloured(data, first)


def _preview(parts: list[Any], device: Any = None) -> bytes:
    from engine.export.preview import to_preview_png

    offsets = np.cumsum([0] + [len(p.vertices_zyx_mm) for p in parts[:-1]])
    verts = np.concatenate([np.asarray(p.vertices_zyx_mm, np.float32) for p in parts])
    faces = np.concatenate([np.asarray(p.faces, np.int64) + o for p, o in zip(parts, offsets, strict=True)])
    return to_preview_png(verts, faces, device=device)


def _centre_xyz(models: LabelModels) -> np.ndarray:
    lo = np.min([p.vertices_xyz.min(axis=0) for p in models.parts], axis=0).astype(np.float64)
    hi = np.max([p.vertices_xyz.max(axis=0) for p in models.parts], axis=0).astype(np.float64)
    out: np.ndarray = (lo + hi) / 2
    return out


def _files(
    models: LabelModels, params: ReconParams, device: Any, tmp: Path, seconds: dict[str, float]
) -> dict[str, dict[str, Any]]:
    """Every file but the report into ``tmp``; their accounts (bytes, faces) by name."""
    centre_zyx = _centre_xyz(models)[::-1]
    export = params.export
    t0 = time.perf_counter()
    whole, _ = copy_parts(models, centre_zyx, None)
    phone, phone_info = copy_parts(models, centre_zyx, export.phone_max_triangles, device)
    ar_models = LabelModels(
        [_as_label(p, lp, centre_zyx) for p, lp in zip(phone, models.parts, strict=True)], models.report
    )
    ar, ar_info = copy_parts(ar_models, centre_zyx, export.ar_max_triangles, device)
    seconds["copies"] = time.perf_counter() - t0
    accounts: dict[str, dict[str, Any]] = {}
    for name, parts, draco, info in (
        (MODEL_GLB, whole, False, None),
        ("phone.glb", phone, True, phone_info),
        ("ar.glb", ar, False, ar_info),
    ):
        t0 = time.perf_counter()
        data = _glb(parts, draco)
        (tmp / name).write_bytes(data)
        accounts[name] = {"faces": int(sum(len(p.faces) for p in parts)), "bytes": len(data)}
        if info is not None:
            accounts[name]["labels"] = info
        seconds[name] = time.perf_counter() - t0
    t0 = time.perf_counter()
    png = _preview(phone, device)
    (tmp / "preview.png").write_bytes(png)
    accounts["preview.png"] = {"bytes": len(png)}
    seconds["preview.png"] = time.perf_counter() - t0
    return accounts


def _as_label(part: Any, label: LabelPart, centre_zyx: np.ndarray) -> LabelPart:
    """A phone copy's part as a ``LabelPart`` again (patient frame), its area that of the label (the share's
    weight)."""
    verts = np.asarray(part.vertices_zyx_mm, np.float64) + centre_zyx
    xyz = np.ascontiguousarray(verts[:, ::-1], np.float32)
    return LabelPart(label.name, label.value, label.color, xyz, np.asarray(part.faces, np.int32), label.stats)


def write_label_outputs(
    models: LabelModels,
    outdir: str | Path,
    params: ReconParams | None = None,
    *,
    device: Any = "auto",
    extra: dict[str, Any] | None = None,
    stl_folder: bool = False,
) -> dict[str, Path]:
    """Write a label job's files (``engine_files(labels=True)``: model.glb, phone.glb, ar.glb, preview.png,
    report.json, labels.zip; see the module docstring) into ``outdir``, all or nothing; ``extra`` goes into the
    report (e.g. ``input``), ``stl_folder`` keeps ``labels/<name>.stl`` beside the zip (the CLI's layout).

    Returns:
        {file name: path}, in the registry's order.

    Raises:
        InputError: a label's mesh cannot be encoded (empty or malformed).
    """
    from engine.report import report_json

    params = params or ReconParams()
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".bonemesh-labels-", dir=out))
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    try:
        accounts = _files(models, params, device, tmp, seconds)
        write_label_stls(models, tmp)
        total = int(sum(len(p.faces) for p in models.parts))
        accounts[LABELS_ZIP] = {"faces": total, "bytes": (tmp / LABELS_ZIP).stat().st_size}
        seconds["total"] = time.perf_counter() - t0
        report = _report(models, params, accounts, seconds, extra)
        (tmp / REPORT_JSON).write_text(report_json(report))  # type: ignore[arg-type]  # a label job's report
        if stl_folder:
            if (out / "labels").exists():
                shutil.rmtree(out / "labels")
            os.replace(tmp / "labels", out / "labels")
        return move_files(tmp, out, engine_files(labels=True))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _report(
    models: LabelModels,
    params: ReconParams,
    accounts: dict[str, dict[str, Any]],
    seconds: dict[str, float],
    extra: dict[str, Any] | None,
) -> dict[str, Any]:
    rows = models.report["labels"]
    frame = {**models.report.get("frame", {}), "gltf_centre_lps_mm": [round(float(c), 6) for c in _centre_xyz(models)]}
    placed = (models.report.get("source") or {}).get("placed_by")
    if placed and placed != "none" and "placed_by" in frame:  # what placed the map (its NIfTI affine, NRRD space...)
        frame["placed_by"] = placed
    return {
        **models.report,
        **(extra or {}),
        "parameters": params.to_dict(),
        "frame": frame,
        "mesh": {
            "n_faces": int(sum(r["faces"] for r in rows)),
            "n_vertices": int(sum(r["vertices"] for r in rows)),
            "watertight": all(bool(r["watertight"]) for r in rows),
            "labels": len(rows),
        },
        "exports": accounts,
        "write_seconds": {k: round(v, 4) for k, v in seconds.items()},
    }
