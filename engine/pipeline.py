"""The EMC33 pipeline: volume in, mesh and report out (``reconstruct``), and the output files (``write_outputs``).

Stages, in order (``STAGES``): preprocess (host: optional crop and slice filters, then the body mask of
``engine.stages.bodymask`` for HU data), upload (the volume, once), gaussian, isosurface
(MC33), decimate (quadric edge collapse), islands (optional, on the decimated mesh), smooth
(surface-preserving Laplacian), normals. Everything after preprocess runs on the device where the data
already is; only the finished mesh comes back. A failing stage raises ``StageError`` naming it (or the raw error
with ``BONEMESH_DEBUG=1``); bad input raises ``InputError``.
"""

from __future__ import annotations

import dataclasses
import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.errors import EmptySurfaceError, InputError, StageError
from engine.level import choose_level, hu_offset
from engine.params import ReconParams
from engine.progress import StageProgress
from engine.types import Mesh, Volume

SEAM_VOXELS = 6  # a budgeted decimation's last pass across the slab groups' borders reaches this far from them
STAGES = ("preprocess", "upload", "gaussian", "isosurface", "decimate", "islands", "smooth", "normals")
Progress = Callable[[str, float], None]


class Reconstruction:
    """The result: the final mesh (with normals) and a JSON-able report.

    ``reconstruct`` leaves the mesh on its device (``device_mesh``: positions, faces, normals as Warp arrays, which
    ``write_outputs`` lays out there); ``mesh`` brings it to the host on first use.
    """

    def __init__(self, mesh: Mesh | None = None, report: dict[str, Any] | None = None, device_mesh: Any = None):
        if mesh is None and device_mesh is None:
            raise ValueError("a Reconstruction needs a mesh or a device mesh")
        self._mesh = mesh
        self.report: dict[str, Any] = {} if report is None else report
        self.device_mesh = device_mesh

    @property
    def mesh(self) -> Mesh:
        if self._mesh is None:
            pos, faces, normals = self.device_mesh  # sync point: the finished mesh comes back
            self._mesh = Mesh(
                pos.numpy().astype(np.float32).reshape(-1, 3),
                faces.numpy().astype(np.int32).reshape(-1, 3),
                normals.numpy().astype(np.float32).reshape(-1, 3),
            )
        return self._mesh

    def __repr__(self) -> str:
        return (
            f"Reconstruction(faces={self.report.get('mesh', {}).get('n_faces')}, device={self.device_mesh is not None})"
        )


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
    budget: int | None = None  # max_device_bytes: the volume is streamed and the mesh decimated within it
    stream: Any = None  # engine.stages.stream.StreamResult of a budgeted run


def reconstruct(
    volume: Volume,
    params: ReconParams | None = None,
    *,
    device: str = "auto",
    on_progress: Progress | None = None,
    max_device_bytes: int | str | None = None,
) -> Reconstruction:
    """Run the EMC33 pipeline on a volume.

    Args:
        volume: the scan (see ``engine.types.Volume``).
        params: pipeline parameters (defaults: the paper's best combination).
        device: "auto", "cpu", "cuda" or "cuda:N".
        on_progress: called as ``on_progress(stage, fraction_done)`` when a stage starts and ends and inside long
            stages (the decimation's passes); the fraction weights stages by their expected time
            (``engine.progress``).
        max_device_bytes: a device memory budget (bytes, or text such as ``"2GiB"``) that every stage keeps to:
            the volume is streamed in z slabs through the Gaussian and MC33, and a mesh whose decimation does not
            fit is decimated in groups of slabs and then in z tiles with pinned borders (``engine.stages.stream``,
            ``engine.stages.tiled``). The volume stages' result is the same as without a budget; the decimation
            keeps the same topology and guards. ``None``: no budget (the whole volume goes up at once). The peak
            used is reported in ``report["memory"]``.

    Returns:
        The final mesh (vertices (z, y, x) mm in the grid, outward faces, unit vertex normals) and the report; the
        report's ``frame`` maps the grid to the patient frame (``engine.orient``, applied by ``write_outputs``).

    Raises:
        InputError: the volume or parameters cannot give a model (EmptySurfaceError: no surface at the level;
            BudgetError: the memory budget is too small, with the smallest that would work).
        StageError: a stage failed otherwise.
    """
    import warp as wp

    from engine.device import resolve_device
    from engine.memory import PeakMemory, parse_bytes

    params = params or ReconParams()
    dev = resolve_device(device)
    budget = parse_bytes(max_device_bytes)
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
    st = _State(volume, budget=budget)
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
    memory = PeakMemory(dev)
    with wp.ScopedDevice(dev):
        memory.start()
        for name in STAGES:

            def within(fraction: float, name: str = name) -> None:
                progress.within(name, fraction)

            progress.start(name)
            t0 = time.perf_counter()
            try:
                with wp.ScopedDevice(dev if st.pos is None else st.pos.device):  # the host, past the budget
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

        with wp.ScopedDevice(st.pos.device):  # sync point: the counts come back
            report["mesh"] = mesh_stats_device(st.pos, st.faces, _incidence(st))
        report["finish_seconds"] = time.perf_counter() - t0
        report["memory"] = {
            "budget_bytes": budget,
            "peak_bytes": memory.peak(),
            "measured_by": memory.how,
            "in_use_before_bytes": memory.baseline,
        }
        memory.stop()
        if st.stream is not None:
            report["memory"]["stream"] = st.stream.info
    report["total_seconds"] = sum(report["stage_seconds"].values())
    return Reconstruction(report=report, device_mesh=(st.pos, st.faces, st.normals))


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
    if st.budget is None:
        st.field = wp.array(np.ascontiguousarray(data))
    else:  # streamed in slabs by the isosurface stage (engine.stages.stream)
        st.volume = dataclasses.replace(st.volume, data=np.ascontiguousarray(data))
    st.level, how = choose_level(st.volume, params)
    report["iso_level"] = {"value": st.level, "units": st.volume.units, "chosen_by": how}


def _gaussian(st: _State, params: ReconParams, report: dict[str, Any], progress: Progress) -> None:
    from engine.stages.gaussian import smooth_volume

    if params.gaussian is not None and st.field is not None:  # (a budgeted run smooths slab by slab)
        st.field = smooth_volume(st.field, params.gaussian)


def _isosurface(st: _State, params: ReconParams, report: dict[str, Any], progress: Progress) -> None:
    from engine.stages.isosurface import IsosurfaceStats, extract_isosurface

    stats = IsosurfaceStats()
    try:  # its ValueErrors are about the data (NaN, checked on the device in the extraction's own pass)
        if st.budget is None:
            v, f = extract_isosurface(
                st.field, st.level, spacing=st.volume.spacing_zyx_mm, closed=params.iso.closed, stats=stats
            )
        else:
            v, f = _stream(st, params, stats)
    except InputError:
        raise
    except ValueError as exc:
        raise InputError(str(exc)) from None
    st.field = None
    if st.stream is not None and st.stream.grouped:  # decimated in groups already
        report["counts"]["isosurface"] = {"vertices": st.stream.mc33_vertices, "faces": st.stream.mc33_faces}
        report["isosurface"] = {"slabs": stats.slabs, "active_blocks": stats.active_blocks, "blocks": stats.blocks}
        return
    if len(f) == 0:
        lo, hi = float(st.volume.data.min()), float(st.volume.data.max())
        raise EmptySurfaceError(
            f"no surface at level {st.level:g} {st.volume.units}: the scan's values run from "
            f"{lo:g} to {hi:g}; choose a level inside that range"
        )
    st.pos, st.faces = v, f
    report["counts"]["isosurface"] = {"vertices": len(v), "faces": len(f)}
    report["isosurface"] = {"slabs": stats.slabs, "active_blocks": stats.active_blocks, "blocks": stats.blocks}


def _stream(st: _State, params: ReconParams, stats: Any) -> tuple[Any, Any]:
    """The Gaussian and MC33 within the budget (``engine.stages.stream``): the device mesh, or (when groups of
    slabs had to be decimated on the way) empty arrays and the groups in ``st.stream``."""
    import warp as wp

    from engine.stages.stream import stream_surface

    dec = params.decimate
    st.stream = stream_surface(
        st.volume.data,
        st.level,
        st.volume.spacing_zyx_mm,
        closed=params.iso.closed,
        gaussian=params.gaussian,
        budget=st.budget,
        ratio=None if dec is None else dec.reduction,
        decimate=dec is not None,
        dev=wp.get_device(),
        stats=stats,
    )
    if st.stream.device is not None:
        return st.stream.device
    return wp.empty(0, dtype=wp.vec3), wp.empty(0, dtype=wp.vec3i)


def _decimate(st: _State, params: ReconParams, report: dict[str, Any], progress: Progress) -> None:
    if st.stream is not None and st.stream.grouped:
        _decimate_tiled(st, params, report)
        return
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


def _decimate_tiled(st: _State, params: ReconParams, report: dict[str, Any]) -> None:
    """Finish a decimation begun in groups of slabs: tiled rounds across their borders, then a last pass."""
    from engine.stages.decimate import TOLERANCE, target_faces
    from engine.stages.tiled import finish_groups

    sr = st.stream
    assert params.decimate is not None and sr is not None and sr.grouped
    n_in = sr.mc33_faces
    target = target_faces(n_in, params.decimate.reduction, params.decimate.max_triangles)
    host, sr.host = sr.host, None
    pieces, sr.pieces = (None if sr.pieces is None else list(sr.pieces)), None  # finish_groups takes them over
    seam_mm = SEAM_VOXELS * max(st.volume.spacing_zyx_mm)
    st.pos, st.faces, info = finish_groups(host, pieces, sr.origin, target, st.budget, sr.borders, seam_mm)
    out = len(st.faces)
    info |= {"input_faces": n_in, "target_faces": target, "achieved_ratio": out / n_in}
    info["limited_by_guards"] = out > target * (1 + TOLERANCE)
    info["method"] = "warp quadric edge collapse in slab groups and z tiles with pinned borders (memory budget)"
    report["decimate"] = info
    report["counts"]["decimate"] = {"vertices": len(st.pos), "faces": out}


def _fit_or_host(st: _State, report: dict[str, Any]) -> None:
    """The finishing stages hold the whole final mesh: within a budget it cannot fit, they run on the host
    (``engine.memory.place``: Warp's CPU device, outside the budget; reported as ``report["finish"]``), or, where
    the device is the host, the job stops early with the budget that would work."""
    from engine.memory import finish_bytes, place
    from engine.stages.devmesh import on_device

    if st.budget is None or st.faces is None:
        return
    what = f"finishing the model ({len(st.faces):,} faces: islands, smoothing, normals, outputs)"
    need = finish_bytes(len(st.faces))
    where, note = place(st.faces.device, need, st.budget, what, " or decimate further")
    if note is not None:
        st.pos, st.faces = on_device(where, st.pos, st.faces)
        st.incidence = None
        report["finish"] = note


def _islands(st: _State, params: ReconParams, report: dict[str, Any], progress: Progress) -> None:
    _fit_or_host(st, report)
    if params.islands is None:
        return
    from engine.stages.islands import remove_islands_device

    min_volume = params.islands.min_volume_for(st.volume.spacing_zyx_mm)
    st.pos, st.faces, info = remove_islands_device(
        st.pos, st.faces, min_volume_mm3=min_volume, keep_largest=params.islands.keep_largest, consume=True
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
