"""The EMC33 pipeline: volume in, mesh and report out (``reconstruct``), and the output files (``write_outputs``).

Stages, in order (``STAGES``): preprocess (host: optional crop and slice filters, then the body mask of
``engine.stages.bodymask`` for HU data), upload (the volume, once), gaussian, isosurface
(MC33), decimate (quadric edge collapse), islands (optional, on the decimated mesh), smooth
(surface-preserving Laplacian), normals. Everything after preprocess runs on the device where the data
already is; only the finished mesh comes back. A failing stage raises ``StageError`` naming it (or the raw error
with ``BONEMESH_DEBUG=1``); bad input raises ``InputError``.
"""

from __future__ import annotations

import os
import platform
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from engine.errors import EmptySurfaceError, InputError, StageError
from engine.level import choose_level, hu_offset
from engine.params import ReconParams
from engine.progress import StageProgress
from engine.types import Mesh, Volume

STAGES = ("preprocess", "upload", "gaussian", "isosurface", "decimate", "islands", "smooth", "normals")
Progress = Callable[[str, float], None]


@dataclass
class Reconstruction:
    """The result: the final mesh (with normals) and a JSON-able report."""

    mesh: Mesh
    report: dict[str, Any] = field(default_factory=dict)


def _versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for name in ("bonemesh", "warp-lang", "numpy", "scikit-image", "pymeshlab", "DracoPy"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = "not installed"
    return out


@dataclass
class _State:
    """What the stages hand on: the volume, then the device field, then the device mesh (and its stars)."""

    volume: Volume
    field: Any = None
    level: float = 0.0
    pos: Any = None  # wp.array(dtype=wp.vec3), (z, y, x) mm
    faces: Any = None  # wp.array(dtype=wp.vec3i)
    incidence: Any = None  # devmesh.Incidence of the current mesh, when built
    normals: Any = None


def reconstruct(
    volume: Volume, params: ReconParams | None = None, *, device: str = "auto", on_progress: Progress | None = None
) -> Reconstruction:
    """Run the EMC33 pipeline on a volume.

    Args:
        volume: the scan (see ``engine.types.Volume``).
        params: pipeline parameters (defaults: the paper's best combination).
        device: "auto", "cpu", "cuda" or "cuda:N".
        on_progress: called as ``on_progress(stage, fraction_done)`` when a stage starts and ends and inside long
            stages (the decimation's passes); the fraction weights stages by their expected time
            (``engine.progress``).

    Returns:
        The final mesh (vertices (z, y, x) mm in the grid, outward faces, unit vertex normals) and the report; the
        report's ``frame`` maps the grid to the patient frame (``engine.orient``, applied by ``write_outputs``).

    Raises:
        InputError: the volume or parameters cannot give a model (EmptySurfaceError: no surface at the level).
        StageError: a stage failed otherwise.
    """
    import warp as wp

    from engine.device import resolve_device

    params = params or ReconParams()
    dev = resolve_device(device)
    report: dict[str, Any] = {
        "parameters": params.to_dict(),
        "device": {"spec": device, "name": str(dev), "description": getattr(dev, "name", str(dev))},
        "versions": _versions(),
        "input": {
            "shape_zyx": list(volume.data.shape),
            "dtype": str(volume.data.dtype),
            "spacing_zyx_mm": list(volume.spacing_zyx_mm),
            "units": volume.units,
            "source": volume.source,
        },
        "stage_seconds": {},
        "counts": {},
    }
    st = _State(volume)
    stages: dict[str, Callable[[_State, ReconParams, dict[str, Any], Progress], None]] = {
        "preprocess": _preprocess,
        "upload": _upload,
        "gaussian": _gaussian,
        "isosurface": _isosurface,
        "decimate": _decimate,
        "islands": _islands,
        "smooth": _smooth,
        "normals": _normals,
    }
    progress = StageProgress(STAGES, on_progress)
    with wp.ScopedDevice(dev):
        for name in STAGES:

            def within(fraction: float, name: str = name) -> None:
                progress.within(name, fraction)

            progress.start(name)
            t0 = time.perf_counter()
            try:
                stages[name](st, params, report, within)
            except (InputError, StageError):
                raise
            except Exception as exc:
                if os.environ.get("BONEMESH_DEBUG") == "1":
                    raise
                raise StageError(name, exc) from exc
            report["stage_seconds"][name] = time.perf_counter() - t0
            progress.end(name)
        t0 = time.perf_counter()
        from engine.stages.devmesh import mesh_stats_device

        report["mesh"] = mesh_stats_device(st.pos, st.faces, _incidence(st))
        verts = st.pos.numpy().astype(np.float32)  # sync point: the finished mesh comes back
        faces = st.faces.numpy().astype(np.int32).reshape(-1, 3)
        normals = st.normals.numpy().astype(np.float32)
        report["finish_seconds"] = time.perf_counter() - t0
    report["total_seconds"] = sum(report["stage_seconds"].values())
    return Reconstruction(Mesh(verts, faces, normals), report)


def _preprocess(st: _State, params: ReconParams, report: dict[str, Any], progress: Progress) -> None:
    from engine.orient import patient_frame
    from engine.stages.preprocess import preprocess_volume

    if params.preprocess is not None:
        st.volume = preprocess_volume(st.volume, params.preprocess)
    report["counts"]["voxels"] = int(st.volume.data.size)
    report["frame"] = patient_frame(st.volume, params.orient).to_dict()  # engine.orient: STL/glTF frames
    if params.body is not None:  # bone of the body only (HU data): engine.stages.bodymask
        from engine.stages.bodymask import isolate_bone

        level = choose_level(st.volume, params)[0]
        st.volume, report["body_mask"] = isolate_bone(st.volume, level, params.body, hu_offset(st.volume, params))


def _upload(st: _State, params: ReconParams, report: dict[str, Any], progress: Progress) -> None:
    import warp as wp

    data = st.volume.data
    if data.dtype not in (np.uint8, np.uint16, np.int16, np.float32):
        data = data.astype(np.float32)
    st.field = wp.array(np.ascontiguousarray(data))
    st.level, how = choose_level(st.volume, params)
    report["iso_level"] = {"value": st.level, "units": st.volume.units, "chosen_by": how}


def _gaussian(st: _State, params: ReconParams, report: dict[str, Any], progress: Progress) -> None:
    from engine.stages.gaussian import smooth_volume

    if params.gaussian is not None:
        st.field = smooth_volume(st.field, params.gaussian)


def _isosurface(st: _State, params: ReconParams, report: dict[str, Any], progress: Progress) -> None:
    from engine.stages.isosurface import IsosurfaceStats, extract_isosurface

    stats = IsosurfaceStats()
    try:  # its ValueErrors are about the data (NaN, checked on the device in the extraction's own pass)
        v, f = extract_isosurface(
            st.field, st.level, spacing=st.volume.spacing_zyx_mm, closed=params.iso.closed, stats=stats
        )
    except ValueError as exc:
        raise InputError(str(exc)) from None
    st.field = None
    if len(f) == 0:
        lo, hi = float(st.volume.data.min()), float(st.volume.data.max())
        raise EmptySurfaceError(
            f"no surface at level {st.level:g} {st.volume.units}: the scan's values run from "
            f"{lo:g} to {hi:g}; choose a level inside that range"
        )
    st.pos, st.faces = v, f
    report["counts"]["isosurface"] = {"vertices": len(v), "faces": len(f)}
    report["isosurface"] = {"slabs": stats.slabs, "active_blocks": stats.active_blocks, "blocks": stats.blocks}


def _decimate(st: _State, params: ReconParams, report: dict[str, Any], progress: Progress) -> None:
    if params.decimate is None:
        return
    from engine.stages.decimate import TOLERANCE, decimate_device, target_faces

    n_in = len(st.faces)
    target = target_faces(n_in, params.decimate.reduction, params.decimate.max_triangles)
    if target >= n_in:
        report["decimate"] = {"input_faces": n_in, "target_faces": target, "output_faces": n_in, "passes": 0}
        return

    def on_pass(faces_now: int) -> None:
        progress((n_in - faces_now) / max(n_in - target, 1))

    st.pos, st.faces, stats = decimate_device(st.pos, st.faces, target, on_pass=on_pass)
    info = stats.to_dict()
    info["achieved_ratio"] = stats.output_faces / n_in
    info["limited_by_guards"] = stats.output_faces > target * (1 + TOLERANCE)
    info["method"] = "warp quadric edge collapse (link condition, border kept, normal turn guard)"
    report["decimate"] = info
    report["counts"]["decimate"] = {"vertices": len(st.pos), "faces": stats.output_faces}


def _islands(st: _State, params: ReconParams, report: dict[str, Any], progress: Progress) -> None:
    if params.islands is None:
        return
    from engine.stages.islands import remove_islands_device

    min_volume = params.islands.min_volume_for(st.volume.spacing_zyx_mm)
    st.pos, st.faces, info = remove_islands_device(
        st.pos, st.faces, min_volume_mm3=min_volume, keep_largest=params.islands.keep_largest
    )
    if len(st.faces) == 0:
        raise EmptySurfaceError("island removal left nothing: lower --min-island-mm3 or keep more pieces")
    report["islands"] = {**info, "min_volume_mm3": min_volume}
    report["counts"]["islands"] = {"vertices": len(st.pos), "faces": len(st.faces)}


def _incidence(st: _State) -> Any:
    from engine.stages.devmesh import Incidence

    if st.incidence is None:
        st.incidence = Incidence(len(st.pos)).build(st.faces, len(st.faces))
    return st.incidence


def _smooth(st: _State, params: ReconParams, report: dict[str, Any], progress: Progress) -> None:
    if params.smooth is None:
        return
    from engine.stages.smooth import smooth_device

    st.pos, report["smooth"] = smooth_device(st.pos, st.faces, params.smooth, _incidence(st))


def _normals(st: _State, params: ReconParams, report: dict[str, Any], progress: Progress) -> None:
    from engine.stages.normals import normals_device

    st.normals = normals_device(st.pos, st.faces, _incidence(st))


def _budget_mesh(mesh: Mesh, max_triangles: int, device: Any) -> tuple[Mesh, dict[str, Any]]:
    """The mesh itself when within budget, else a decimated copy with fresh normals, made on the device.

    The copy continues the print model's decimation with every guard. Topology-preserving decimation cannot shrink
    a closed piece below a tetrahedron, so a scan with thousands of specks cannot reach a phone-sized budget: then
    the smallest pieces (by volume) are dropped, halving the number kept, and the rest decimated again, until the
    budget is met (each round works on the already small copy). Where pieces of high genus still keep the copy over
    budget (every tunnel keeps a ring of faces), the copy is clustered (``engine.stages.cluster``:
    ``topology_preserved`` false, small tunnels close). The print model keeps every piece and every guard.
    """
    if len(mesh.faces) <= max_triangles:
        return mesh, {"faces": len(mesh.faces), "decimated": False}
    import warp as wp

    from engine.stages.decimate import decimate_device
    from engine.stages.islands import remove_islands_device
    from engine.stages.normals import normals_device

    with wp.ScopedDevice(device):
        pos, faces, stats = decimate_device(
            wp.array(mesh.vertices, dtype=wp.vec3), wp.array(mesh.faces, dtype=wp.vec3i), max_triangles
        )
        passes = stats.passes
        keep: int | None = None
        pieces: int | None = None
        dropped = 0
        while len(faces) > max_triangles and keep != 1:
            if pieces is None:
                pieces = remove_islands_device(pos, faces)[2]["pieces_before"]
            if pieces <= 1:
                break
            keep = (
                max(1, min(pieces // 2, max_triangles // 200)) if keep is None else max(1, min(keep // 2, pieces - 1))
            )
            pos, faces, isl = remove_islands_device(pos, faces, keep_largest=keep)
            dropped += int(isl["removed_pieces"])
            pieces = int(isl["pieces_after"])
            pos, faces, stats = decimate_device(pos, faces, max_triangles)
            passes += stats.passes
        summary: dict[str, Any] = {"topology_preserved": True}
        if len(faces) > max_triangles:  # pieces of high genus: this viewing copy may close tunnels to meet the budget
            from engine.stages.cluster import cluster_device

            pos, faces, summary["clustered"] = cluster_device(pos, faces, max_triangles)
            summary["topology_preserved"] = False
        normals = normals_device(pos, faces).numpy()  # sync point: the copy comes back
        dv, df = pos.numpy(), faces.numpy().astype(np.int32).reshape(-1, 3)
    summary.update(
        faces=len(df),
        decimated=True,
        passes=passes,
        pieces_dropped=dropped,
        over_budget=len(df) > max_triangles,
    )
    return Mesh(np.ascontiguousarray(dv, np.float32), df, normals.astype(np.float32)), summary


def write_outputs(
    recon: Reconstruction, outdir: str | Path, params: ReconParams | None = None, *, device: str = "auto"
) -> dict[str, Path]:
    """Write model.stl, model.glb, phone.glb (Draco), ar.glb, phone_meshopt.glb, model.usdz, preview.png and
    report.json into ``outdir``.

    Every file is written into a temporary folder inside ``outdir`` and moved into place only when all are
    complete: a failure leaves no partial model.
    """
    import json

    from engine.device import resolve_device
    from engine.export import to_draco_glb, to_glb, to_stl
    from engine.export.printcheck import PRINT_STL, check_print_model, stl_name
    from engine.export.viewers import viewer_files

    params = params or ReconParams()
    dev = resolve_device(device)
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".bonemesh-", dir=out))
    try:
        from engine.orient import export_meshes

        # the STL in patient LPS mm, the glTF files in patient axes centred on the model (engine.orient)
        p, m, recon.report["frame"] = export_meshes(recon.mesh, recon.report.get("frame"))
        if stl_name(params) == PRINT_STL:  # an unprintable print model fails here (PrintCheckError), unwritten
            recon.report["print_check"] = check_print_model(p.vertices, p.faces, recon.report.get("mesh"))
        phone, phone_info = _budget_mesh(m, params.export.phone_max_triangles, dev)
        ar, ar_info = _budget_mesh(phone, params.export.ar_max_triangles, dev)
        recon.report["exports"] = {"phone.glb": phone_info, "ar.glb": ar_info}
        files = {
            stl_name(params): to_stl(p.vertices, p.faces, header="bonemesh model, patient LPS frame, mm"),
            "model.glb": to_glb(m.vertices, m.faces, m.normals),
            "phone.glb": to_draco_glb(phone.vertices, phone.faces, phone.normals),
            "ar.glb": to_glb(ar.vertices, ar.faces, ar.normals),
        }
        files.update(viewer_files(phone, ar))  # meshopt GLB, USDZ, preview.png (engine.export.viewers)
        for name, data in files.items():
            (tmp / name).write_bytes(data)
        recon.report["exports"].update(
            {name: {**recon.report["exports"].get(name, {}), "bytes": len(data)} for name, data in files.items()}
        )
        (tmp / "report.json").write_text(json.dumps(recon.report, indent=2, default=_json_default) + "\n")
        paths = {}
        for name in [*files, "report.json"]:
            os.replace(tmp / name, out / name)
            paths[name] = out / name
        return paths
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
