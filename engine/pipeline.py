"""The EMC33 pipeline: volume in, mesh and report out (``reconstruct``), and the output files (``write_outputs``).

Stages, in order (``STAGES``): preprocess (host, optional), upload, gaussian (device), isosurface (MC33, device),
islands (host, optional), decimate (host, quadric error), smooth (device, surface-preserving Laplacian),
normals (device). A failing stage raises ``StageError`` naming it (or the raw error with ``BONEMESH_DEBUG=1``);
bad input raises ``InputError``.
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

from engine.errors import EngineError, InputError
from engine.params import ISO_PRESETS_HU, ReconParams
from engine.types import Mesh, Volume

STAGES = ("preprocess", "upload", "gaussian", "isosurface", "islands", "decimate", "smooth", "normals")
Progress = Callable[[str, float], None]


class StageError(EngineError):
    """A pipeline stage failed for a reason that is not the input's fault."""

    def __init__(self, stage: str, cause: BaseException) -> None:
        super().__init__(f"stage '{stage}' failed: {type(cause).__name__}: {cause}")
        self.stage = stage


class EmptySurfaceError(InputError):
    """The iso level does not cross the data: there is no surface to build."""


@dataclass
class Reconstruction:
    """The result: the final mesh (with normals) and a JSON-able report."""

    mesh: Mesh
    report: dict[str, Any] = field(default_factory=dict)


def choose_level(volume: Volume, params: ReconParams) -> tuple[float, str]:
    """The iso level in the volume's units and how it was chosen."""
    iso = params.iso
    if iso.iso is not None:
        return float(iso.iso), "given"
    preset = iso.preset
    if preset is None and volume.units == "HU":
        preset = "bone"
    if preset is not None:
        hu = ISO_PRESETS_HU[preset]
        if volume.units == "HU":
            return hu, f"preset {preset} ({hu:g} HU)"
        if iso.hu_offset is not None:
            return hu + iso.hu_offset, f"preset {preset} ({hu:g} HU + offset {iso.hu_offset:g})"
        raise InputError(
            f"preset '{preset}' is in HU but this volume is not calibrated in HU: give --iso in its units, "
            "or --hu-offset if it stores HU plus an offset (1024 for most PNG exports)"
        )
    from skimage.filters import threshold_otsu

    step = max(1, round((volume.data.size / 4_000_000) ** (1 / 3)))
    sample = volume.data[::step, ::step, ::step]
    if sample.min() == sample.max():
        raise EmptySurfaceError(f"the volume is constant ({sample.min()}): there is no surface to build")
    return float(threshold_otsu(sample.ravel())), "Otsu"


def _versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for name in ("bonemesh", "warp-lang", "numpy", "scikit-image", "pymeshlab", "DracoPy"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = "not installed"
    return out


def reconstruct(
    volume: Volume, params: ReconParams | None = None, *, device: str = "auto", on_progress: Progress | None = None
) -> Reconstruction:
    """Run the EMC33 pipeline on a volume.

    Args:
        volume: the scan (see ``engine.types.Volume``).
        params: pipeline parameters (defaults: the paper's best combination).
        device: "auto", "cpu", "cuda" or "cuda:N".
        on_progress: called as ``on_progress(stage, fraction_done)`` when a stage starts and ends.

    Returns:
        The final mesh (vertices (z, y, x) mm, outward faces, unit vertex normals) and the report.

    Raises:
        InputError: the volume or parameters cannot give a model (EmptySurfaceError: no surface at the level).
        StageError: a stage failed otherwise.
    """
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
    state: dict[str, Any] = {"volume": volume}
    done = 0

    def run(name: str, fn: Callable[[], None]) -> None:
        nonlocal done
        if on_progress:
            on_progress(name, done / len(STAGES))
        t0 = time.perf_counter()
        try:
            fn()
        except (InputError, StageError):
            raise
        except Exception as exc:
            if os.environ.get("BONEMESH_DEBUG") == "1":
                raise
            raise StageError(name, exc) from exc
        report["stage_seconds"][name] = time.perf_counter() - t0
        done += 1
        if on_progress:
            on_progress(name, done / len(STAGES))

    def preprocess() -> None:
        from engine.stages.preprocess import preprocess_volume

        if params.preprocess is not None:
            state["volume"] = preprocess_volume(state["volume"], params.preprocess)
        report["counts"]["voxels"] = int(state["volume"].data.size)

    def upload() -> None:
        import warp as wp

        data = state["volume"].data
        if data.dtype not in (np.uint8, np.uint16, np.int16, np.float32):
            data = data.astype(np.float32)
        state["field"] = wp.array(np.ascontiguousarray(data), device=dev)
        level, how = choose_level(state["volume"], params)
        report["iso_level"] = {"value": level, "units": state["volume"].units, "chosen_by": how}
        state["level"] = level

    def gaussian() -> None:
        from engine.stages.gaussian import smooth_volume

        if params.gaussian is not None:
            state["field"] = smooth_volume(state["field"], params.gaussian)

    def isosurface() -> None:
        from engine.stages.isosurface import IsosurfaceStats, extract_isosurface

        st = IsosurfaceStats()
        try:  # its ValueErrors are about the data (NaN, checked on the device in the extraction's own pass)
            v, f = extract_isosurface(
                state["field"],
                state["level"],
                spacing=state["volume"].spacing_zyx_mm,
                closed=params.iso.closed,
                stats=st,
            )
        except ValueError as exc:
            raise InputError(str(exc)) from None
        verts = v.numpy().reshape(-1, 3).astype(np.float32)  # sync point (the mesh goes to the host stages)
        faces = f.numpy().reshape(-1, 3).astype(np.int32)
        del state["field"]
        if len(faces) == 0:
            lo, hi = float(state["volume"].data.min()), float(state["volume"].data.max())
            raise EmptySurfaceError(
                f"no surface at level {state['level']:g} {state['volume'].units}: the scan's values run from "
                f"{lo:g} to {hi:g}; choose a level inside that range"
            )
        state["verts"], state["faces"] = verts, faces
        report["counts"]["isosurface"] = {"vertices": len(verts), "faces": len(faces)}
        report["isosurface"] = {"slabs": st.slabs, "active_blocks": st.active_blocks, "blocks": st.blocks}

    def islands() -> None:
        if params.islands is None:
            return
        from engine.stages.islands import remove_islands

        v, f, info = remove_islands(
            state["verts"],
            state["faces"],
            min_volume_mm3=params.islands.min_volume_mm3,
            keep_largest=params.islands.keep_largest,
        )
        if len(f) == 0:
            raise EmptySurfaceError("island removal left nothing: lower --min-island-mm3 or keep more pieces")
        state["verts"], state["faces"] = v, f
        report["islands"] = info
        report["counts"]["islands"] = {"vertices": len(v), "faces": len(f)}

    def decimate() -> None:
        if params.decimate is None:
            return
        from engine.stages.decimate import decimate_mesh

        v, f, info = decimate_mesh(
            state["verts"],
            state["faces"],
            reduction=params.decimate.reduction,
            max_triangles=params.decimate.max_triangles,
        )
        state["verts"], state["faces"] = v, f
        report["decimate"] = info
        report["counts"]["decimate"] = {"vertices": len(v), "faces": len(f)}

    def smooth() -> None:
        if params.smooth is None:
            return
        from engine.stages.smooth import smooth_mesh

        state["verts"], info = smooth_mesh(state["verts"], state["faces"], params.smooth, dev)
        report["smooth"] = info

    def normals() -> None:
        from engine.stages.normals import vertex_normals

        state["normals"] = vertex_normals(state["verts"], state["faces"], dev)

    for name, fn in zip(
        STAGES, (preprocess, upload, gaussian, isosurface, islands, decimate, smooth, normals), strict=True
    ):
        run(name, fn)
    from engine.stages.meshcheck import mesh_stats

    report["mesh"] = mesh_stats(state["verts"], state["faces"])
    report["total_seconds"] = sum(report["stage_seconds"].values())
    return Reconstruction(Mesh(state["verts"], state["faces"], state["normals"]), report)


def _budget_mesh(mesh: Mesh, max_triangles: int, device: Any) -> tuple[Mesh, dict[str, Any]]:
    """The mesh itself when within budget, else a decimated copy with fresh normals.

    Topology-preserving decimation cannot shrink a closed piece below a tetrahedron, so a scan with thousands of
    specks cannot reach a phone-sized budget. Then the smallest pieces (by volume) of the decimated copy are
    dropped, halving the number kept, and the rest decimated again, until the budget is met; each round works on
    the already reduced copy, so a 30 M-face model costs one large decimation. Where one piece of high genus
    still keeps the copy over budget, the copy is decimated without the topology guard (``topology_preserved``
    false: it may close small tunnels). The report says how many pieces were dropped (the print model keeps them
    all and is never decimated without the guard).
    """
    if len(mesh.faces) <= max_triangles:
        return mesh, {"faces": len(mesh.faces), "decimated": False}
    from engine.stages.decimate import decimate_mesh
    from engine.stages.islands import remove_islands
    from engine.stages.meshcheck import component_labels
    from engine.stages.normals import vertex_normals

    dv, df, info = decimate_mesh(mesh.vertices, mesh.faces, max_triangles=max_triangles)
    keep: int | None = None
    dropped = 0
    while len(df) > max_triangles and keep != 1:
        pieces = component_labels(df, len(dv))[0]
        if pieces <= 1:
            break
        keep = max(1, min(pieces // 2, max_triangles // 200)) if keep is None else max(1, min(keep // 2, pieces - 1))
        dv, df, isl = remove_islands(dv, df, keep_largest=keep)
        dropped += int(isl["removed_pieces"])
        dv, df, info = decimate_mesh(dv, df, max_triangles=max_triangles)
    topology_kept = True
    if len(df) > max_triangles:  # a piece of high genus: this viewing copy may close tunnels to meet the budget
        from engine.stages.decimate import decimate_for_viewing

        dv, df = decimate_for_viewing(dv, df, max_triangles)
        topology_kept = False
    summary = {
        "faces": len(df),
        "decimated": True,
        "pieces_dropped": dropped,
        "topology_preserved": topology_kept,
        "over_budget": len(df) > max_triangles,
        "decimate": info,
    }
    return Mesh(dv, df, vertex_normals(dv, df, device)), summary


def write_outputs(
    recon: Reconstruction, outdir: str | Path, params: ReconParams | None = None, *, device: str = "auto"
) -> dict[str, Path]:
    """Write model.stl, model.glb, phone.glb (Draco), ar.glb and report.json into ``outdir``.

    Every file is written into a temporary folder inside ``outdir`` and moved into place only when all are
    complete: a failure leaves no partial model.
    """
    import json

    from engine.device import resolve_device
    from engine.export import to_draco_glb, to_glb, to_stl
    from engine.export.printcheck import PRINT_STL, check_print_model, stl_name

    params = params or ReconParams()
    dev = resolve_device(device)
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".bonemesh-", dir=out))
    try:
        m = recon.mesh
        if stl_name(params) == PRINT_STL:  # an unprintable print model fails here (PrintCheckError), unwritten
            recon.report["print_check"] = check_print_model(m.vertices, m.faces, recon.report.get("mesh"))
        phone, phone_info = _budget_mesh(m, params.export.phone_max_triangles, dev)
        ar, ar_info = _budget_mesh(phone, params.export.ar_max_triangles, dev)
        recon.report["exports"] = {"phone.glb": phone_info, "ar.glb": ar_info}
        files = {
            stl_name(params): to_stl(m.vertices, m.faces),
            "model.glb": to_glb(m.vertices, m.faces, m.normals),
            "phone.glb": to_draco_glb(phone.vertices, phone.faces, phone.normals),
            "ar.glb": to_glb(ar.vertices, ar.faces, ar.normals),
        }
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
