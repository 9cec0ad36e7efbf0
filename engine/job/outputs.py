"""The files of a reconstruction (``write_outputs``): ``model.stl`` (patient LPS mm, checked for printing),
``model.glb``, ``phone.glb`` (Draco), ``ar.glb``, the other viewers' files (``phone_meshopt.glb``, ``model.usdz``,
``preview.png``: ``engine.export.viewers``) and ``report.json`` (``engine.report``): the files of the registry
``engine.export.files``, in its order.

The finished mesh is laid out for its files on the device where the pipeline left it (``lay_out``: the patient
frame, the STL's facet records and the glTF buffers, ``engine.export.kernels.layout``); only those buffers come
back. A thread then streams the print model's two files to disk while the device makes the phone and AR copies
(``engine.decimation.viewing``: guarded decimation where the topology can be kept within the budget, else
clustering, the AR copy then clustered from the same mesh as the phone copy) and the host encodes them. Every file
goes into a temporary folder inside the output folder and is moved into place only when all are complete: a
failure leaves no partial model.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from engine.budget import LAYOUT_CHUNK_FACES, Budget, BudgetSpec
from engine.decimation.viewing import viewing_copies
from engine.export.files import MODEL_GLB, REPORT_JSON, VIEWING_ENTRY, engine_files, move_files
from engine.params import ReconParams
from engine.report import ExportInfo, MeshStats, Report, report_json
from engine.types import Mesh

if TYPE_CHECKING:
    from engine.device import DeviceSpec
    from engine.job.pipeline import Reconstruction
    from engine.staging import HostCopies

STL_HEADER = "bonemesh model, patient LPS frame, mm"


@dataclass
class Layout:
    """The print model laid out on the device: patient positions (z, y, x) mm and outward faces (``pos``,
    ``faces``), the viewing mesh (patient axes, centred: ``view_pos``, ``view_normals``), the centre (x, y, z) mm,
    and on the host the STL facets (F, 12), the glTF positions (m), normals and their bounds, and the zero-area
    face count; ``seconds``: the device work (``kernels``) and the copies to the host (``copies``)."""

    pos: Any
    faces: Any
    view_pos: Any
    view_normals: Any
    centre_xyz: np.ndarray
    facets: np.ndarray
    gltf_pos: np.ndarray
    gltf_normals: np.ndarray
    gltf_bounds: dict[str, list[float]]
    tris: np.ndarray
    zero_area: int
    seconds: dict[str, float]


def layout_host_bytes(n_vertices: int, n_faces: int) -> int:
    """The host bytes of a ``Layout``'s arrays (STL facets, glTF positions, normals and indices), with room for
    their alignment in ``engine.staging``."""
    from engine.staging import ALIGN

    return n_faces * 60 + n_vertices * 24 + 4 * ALIGN


def lay_out(
    pos: Any,
    faces: Any,
    normals: Any,
    frame: Any,
    to_host: HostCopies | None = None,
    chunk_faces: int = LAYOUT_CHUNK_FACES,
) -> Layout:
    """Map a device mesh (grid (z, y, x) mm, unit normals; on any ``engine.backend``) into the patient frame
    (``engine.orient.Frame``) and lay out its file buffers; the host arrays come back in one sync (on Warp through
    ``to_host``: pinned memory where it holds some, ``engine.staging``); the STL's facets go to the host
    ``chunk_faces`` at a time (``Costs.layout_chunk_faces``)."""
    from engine.backend.base import VEC3F, VEC3I
    from engine.export import kernel_specs as kx
    from engine.export.glb import MM_TO_M
    from engine.surface.devmesh import bounds
    from engine.surface.ops import backend_of

    t0 = time.perf_counter()
    bk = backend_of(pos)
    n, nf = len(pos), len(faces)
    m = bk.empty(12, np.float64)  # the map (row-major), then the offset
    bk.upload(m, np.concatenate([frame.matrix.ravel(), frame.offset_mm]).astype(np.float64))
    patient = bk.empty(n, VEC3F)
    bk.launch(kx.AFFINE_POINTS, n, [pos, m, patient])
    if frame.mirrored:
        wound = bk.empty(nf, VEC3I)
        bk.launch(kx.REVERSE_FACES, nf, [faces, wound])
        faces = wound
    turned = bk.empty(n, VEC3F)
    bk.launch(kx.ROTATE_VECTORS, n, [normals, m, turned])
    lo, hi = bounds(patient)  # sync point: 24 bytes
    centre = (lo.astype(np.float64) + hi.astype(np.float64)) / 2 if n else np.zeros(3)
    shift = bk.empty(12, np.float64)
    bk.upload(shift, np.concatenate([np.eye(3).ravel(), -centre[::-1]]))  # centre is (z, y, x)
    view = bk.empty(n, VEC3F)
    bk.launch(kx.AFFINE_POINTS, n, [patient, shift, view])
    gpos = bk.empty(n, VEC3F)
    gnrm = bk.empty(n, VEC3F)
    scale = bk.empty(1, np.float64)  # float64 by value is not portable through the interface: one element
    bk.upload(scale, np.array([MM_TO_M]))
    bk.launch(kx.GLTF_VERTICES, n, [view, turned, scale, gpos, gnrm])
    glo, ghi = bounds(gpos)  # sync point: every kernel above has run
    t1 = time.perf_counter()
    copies = _copies_for(bk, to_host)
    host = [copies(a) for a in (gpos, gnrm, faces)]
    del gpos, gnrm
    # the STL's facet records (48 B a face) go to the host a chunk at a time, never whole on the device
    facets, host_facets = copies.empty((nf, 12), np.float32)
    chunk = bk.empty((max(min(nf, chunk_faces), 1), 12), np.float32)
    zero_area = bk.zeros(1, np.int32)
    for first in range(0, nf, len(chunk)):
        k = min(len(chunk), nf - first)
        bk.launch(kx.STL_FACETS, k, [patient, faces, first, chunk, zero_area])
        copies.rows(facets, first, chunk, k)  # stream-ordered: the next chunk waits for this copy
    copies.wait()
    gltf_pos, gltf_normals, tris = (a.reshape(-1, 3) for a in host)
    lay = Layout(
        pos=patient,
        faces=faces,
        view_pos=view,
        view_normals=turned,
        centre_xyz=centre[::-1],
        facets=host_facets,
        gltf_pos=gltf_pos,
        gltf_normals=gltf_normals,
        gltf_bounds={"min": [float(x) for x in glo], "max": [float(x) for x in ghi]},
        tris=tris,
        zero_area=int(bk.to_host(zero_area)[0]),
        seconds={"kernels": t1 - t0},
    )
    lay.seconds["copies"] = time.perf_counter() - t1
    lay.seconds["pinned"] = float(copies.pinned)
    return lay


class _WarpCopies:
    """``lay_out``'s copies to the host on Warp: ``engine.staging.HostCopies`` (pinned where it holds a buffer),
    chunks of rows copied in stream order."""

    def __init__(self, to_host: HostCopies) -> None:
        self.to_host, self.pinned = to_host, to_host.pinned

    def __call__(self, arr: Any) -> np.ndarray:
        return self.to_host(arr)

    def empty(self, shape: tuple[int, ...], dtype: Any) -> tuple[Any, np.ndarray]:
        import warp as wp

        return self.to_host.empty(shape, wp.dtype_from_numpy(np.dtype(dtype)))

    def rows(self, dest: Any, first: int, chunk: Any, k: int) -> None:
        import warp as wp

        wp.copy(dest[first : first + k], chunk[:k])

    def wait(self) -> None:
        self.to_host.wait()


class _BackendCopies:
    """``lay_out``'s copies to the host on another backend (OpenCL): plain numpy arrays, each copy a sync."""

    pinned = False

    def __init__(self, bk: Any) -> None:
        self.bk = bk

    def __call__(self, arr: Any) -> np.ndarray:
        out: np.ndarray = self.bk.to_host(arr)
        return out

    def empty(self, shape: tuple[int, ...], dtype: Any) -> tuple[Any, np.ndarray]:
        out = np.empty(shape, dtype)
        return out, out

    def rows(self, dest: Any, first: int, chunk: Any, k: int) -> None:
        dest[first : first + k] = self.bk.to_host(chunk, k)

    def wait(self) -> None:
        self.bk.synchronize()


def _copies_for(bk: Any, to_host: HostCopies | None) -> _WarpCopies | _BackendCopies:
    """How ``lay_out`` copies to the host on ``bk``."""
    if bk.kind != "warp":
        return _BackendCopies(bk)
    from engine.staging import HostCopies

    return _WarpCopies(to_host or HostCopies(None, bk.device))


def _host_mesh(pos: Any, faces: Any, normals: Any = None) -> Mesh:
    from engine.backend.select import backend_of
    from engine.surface.normals import normals_device

    if normals is None:
        normals = normals_device(pos, faces)
    be = backend_of(pos)
    return Mesh(
        np.ascontiguousarray(be.to_host(pos), np.float32).reshape(-1, 3),
        be.to_host(faces).astype(np.int32).reshape(-1, 3),
        np.ascontiguousarray(be.to_host(normals), np.float32).reshape(-1, 3),
    )


def _device_mesh(recon: Reconstruction, dev: Any) -> tuple[Any, Any, Any]:
    """The reconstruction's mesh on ``dev``: the pipeline's own arrays (copied across where they are on another
    device, e.g. a model finished on the host), else uploaded (with fresh normals when it has none)."""
    from engine.backend.base import VEC3F, VEC3I
    from engine.backend.select import get_backend
    from engine.export.glb import check_mesh
    from engine.surface.devmesh import on_device
    from engine.surface.normals import normals_device

    held = recon.device_mesh
    if held is not None:
        return on_device(dev, *held)
    mesh = recon.mesh
    check_mesh(mesh.vertices, mesh.faces, mesh.normals)  # InputError: empty, malformed, out-of-range indices
    be = get_backend(dev)
    pos: Any = be.from_host(np.ascontiguousarray(mesh.vertices, np.float32), VEC3F)
    faces: Any = be.from_host(np.ascontiguousarray(mesh.faces, np.int32), VEC3I)
    if mesh.normals is None:
        return pos, faces, normals_device(pos, faces)
    return pos, faces, be.from_host(np.ascontiguousarray(mesh.normals, np.float32), VEC3F)


def _write_print_files(tmp: Path, stl: str, lay: Layout, parts: list[Any]) -> dict[str, int]:
    """The print model's STL and its full-resolution GLB (with ``parts`` beside the model: the defect template),
    streamed from the laid-out buffers (no Warp here: this runs in a thread beside the device work)."""
    from engine.export.glb import add_parts, mesh_document, write_glb
    from engine.export.stl import write_stl

    sizes = {}
    with open(tmp / stl, "wb") as fh:
        sizes[stl] = write_stl(fh, lay.facets, STL_HEADER)
    document, buffer = mesh_document(lay.gltf_pos, lay.gltf_normals, lay.tris, bounds=lay.gltf_bounds)
    add_parts(document, buffer, parts)
    with open(tmp / MODEL_GLB, "wb") as fh:
        sizes[MODEL_GLB] = write_glb(fh, document, buffer)
    return sizes


def _defect_files(recon: Reconstruction, tmp: Path) -> dict[str, int]:
    """The defect step's files (``engine.defect.step``: ``defect.json``, ``implant.stl`` with a template) written
    into ``tmp``; their sizes by name (none when the reconstruction did not look for a defect)."""
    if recon.defect is None:
        return {}
    sizes = {}
    for name, data in recon.defect.files().items():
        (tmp / name).write_bytes(data)
        sizes[name] = len(data)
    return sizes


def _template_parts(
    recon: Reconstruction, centre_xyz: np.ndarray, budgets: dict[str, int | None], dev: Any
) -> dict[str, list[Any]]:
    """The defect template as a glTF part for each file family (``"print"``: whole; ``"phone"``, ``"ar"``: at its
    share of the copy's budget, ``engine.defect.step.view_faces``), centred as the glTF files are."""
    from engine.defect.step import view_faces

    if recon.defect is None or recon.defect.result is None:
        return {}
    centre_zyx = centre_xyz[::-1]
    return {
        source: [recon.defect.part(centre_zyx, None if budget is None else view_faces(budget), dev)]
        for source, budget in budgets.items()
    }


def write_outputs(
    recon: Reconstruction,
    outdir: str | Path,
    params: ReconParams | None = None,
    *,
    device: DeviceSpec = "auto",
    max_device_bytes: BudgetSpec = None,
) -> dict[str, Path]:
    """Write model.stl, model.glb, phone.glb (Draco), ar.glb, phone_meshopt.glb, model.usdz, preview.png and
    report.json into ``outdir`` (within ``max_device_bytes`` of device memory: bytes, text such as ``"2GiB"`` or an
    ``engine.budget.Budget``, as ``reconstruct``).

    Raises:
        PrintCheckError: the print model is not printable (nothing is written).
        InputError: an empty or malformed mesh (BudgetError: the model cannot be laid out within the budget).
    """
    import warp as wp

    from engine.device import resolve_backend, resolve_device
    from engine.export.files import load_exporters, viewing_files
    from engine.export.printcheck import PRINT_STL, check_print_model, stl_name
    from engine.orient import Frame
    from engine.surface.devmesh import mesh_stats_device

    params = params or ReconParams()
    dev = resolve_device(device)
    be = resolve_backend(device)
    target = dev if be.kind == "warp" else be  # OpenCL: the layout and the viewing copies run on its device
    load_exporters(viewing_files())  # native libraries loaded on this thread, before the print files' writer starts
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".bonemesh-", dir=out))
    report = recon.report
    seconds: dict[str, float | dict[str, float]] = {}
    t0 = time.perf_counter()
    try:
        budget = Budget.of(max_device_bytes)
        where, on_host = _layout_device(recon, target, budget, report)  # the host, past the budget
        with wp.ScopedDevice(where if isinstance(where, wp.Device) else dev):
            pos, faces, normals = _device_mesh(recon, where)
            frame = report.get("frame")
            with _host_copies(where, layout_host_bytes(len(pos), len(faces))) as to_host:
                lay = lay_out(pos, faces, normals, Frame.from_dict(frame), to_host, budget.costs.layout_chunk_faces)
                # the STL in patient LPS mm, the glTF files in patient axes centred on the model (engine.orient)
                report["frame"] = {
                    **(frame or Frame.from_dict(None).to_dict()),
                    "gltf_centre_lps_mm": [round(float(c), 6) for c in lay.centre_xyz],
                }
                stats = report.get("mesh") or mesh_stats_device(lay.pos, lay.faces)
                stl = stl_name(params)
                if stl == PRINT_STL:  # an unprintable print model fails here (PrintCheckError), unwritten
                    report["print_check"] = check_print_model(None, None, stats, zero_area=lay.zero_area)
                seconds["layout"] = time.perf_counter() - t0
                seconds.update({f"layout_{k}": v for k, v in lay.seconds.items()})
                export = params.export
                budgets = {"print": None, "phone": export.phone_max_triangles, "ar": export.ar_max_triangles}
                parts = _template_parts(recon, lay.centre_xyz, budgets, dev)
                # under a host memory bound the files are made one at a time, each let go of before the next (their
                # buffers grow with the model); otherwise the print files are written beside the viewing copies
                one_at_a_time = budget.host_bytes is not None
                with ThreadPoolExecutor(1, thread_name_prefix="bonemesh-write") as pool:
                    writing = pool.submit(_write_print_files, tmp, stl, lay, parts.pop("print", []))
                    if one_at_a_time:
                        writing.result()
                    held = 0 if on_host else budget.costs.held * len(lay.faces)
                    room = budget.beside(held)  # beside the model, where it is on the device
                    views = target if not on_host else dev  # as the model: where it was laid out, or the job's
                    small, infos = _viewing_files(lay, stats, params, room, tmp, seconds, views, parts, one_at_a_time)
                    t1 = time.perf_counter()
                    sizes = writing.result()
                    seconds["wait_print_files"] = time.perf_counter() - t1
        sizes.update(small)
        sizes.update(_defect_files(recon, tmp))
        report["exports"] = infos
        report["exports"].update({name: {**report["exports"].get(name, {}), "bytes": n} for name, n in sizes.items()})
        seconds["total"] = time.perf_counter() - t0
        report["write_seconds"] = seconds
        (tmp / REPORT_JSON).write_text(report_json(report))
        names = engine_files(closed=params.iso.closed, defect=recon.defect is not None)
        return move_files(tmp, out, [n for n in names if n in sizes or n == REPORT_JSON])  # no implant.stl: none made
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _viewing_files(
    lay: Layout,
    stats: MeshStats,
    params: ReconParams,
    room: Budget,
    tmp: Path,
    seconds: dict[str, float | dict[str, float]],
    dev: Any,
    parts: dict[str, list[Any]],
    one_at_a_time: bool = False,
) -> tuple[dict[str, int], dict[str, ExportInfo]]:
    """The phone and AR copies (decimated on ``dev`` within ``room`` bytes) and the small files made from them,
    written into ``tmp`` (encoded ``one_at_a_time`` under a host memory bound): ``({name: size}, {"phone.glb": how
    the copy was made, "ar.glb": ...})``; their seconds go into ``seconds``."""
    t1 = time.perf_counter()
    closed = bool(stats.get("watertight")) and bool(stats.get("manifold"))
    budgets = [params.export.phone_max_triangles, params.export.ar_max_triangles]
    (ppos, pfaces, phone_info), (apos, afaces, ar_info) = viewing_copies(
        lay.view_pos, lay.faces, budgets, stats.get("components"), closed, room, dev
    )
    keep_normals = lay.view_normals if ppos is lay.view_pos else None
    phone = _host_mesh(ppos, pfaces, keep_normals)
    ar = phone if apos is ppos else _host_mesh(apos, afaces)
    seconds["viewing_copies"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    sizes, seconds["encode_parts"] = _encode_small(phone, ar, parts, dev, tmp, one_at_a_time)
    seconds["encode_small"] = time.perf_counter() - t1
    return sizes, {VIEWING_ENTRY["phone"]: phone_info, VIEWING_ENTRY["ar"]: ar_info}


def _encode_small(
    phone: Mesh, ar: Mesh, parts: dict[str, list[Any]], dev: Any, tmp: Path, one_at_a_time: bool = False
) -> tuple[dict[str, int], dict[str, float]]:
    """The small files (``engine.export.viewers.small_files``) written into ``tmp``: each one's size and seconds.
    Those whose exporter runs Warp kernels (``OutputFile.device``: the preview) run on this thread, the others at
    the same time in threads (their codecs are native code and numpy; no Warp call leaves this thread: Warp copies
    from a second thread while this one launched kernels hung ``write_outputs`` on the H100 host, c683f09), or one
    thread ``one_at_a_time``. Each file is written as soon as it is encoded, and its bytes let go of."""
    from engine.export.files import FILES
    from engine.export.viewers import small_files

    def made(name: str, encode: Any) -> tuple[int, float]:
        t0 = time.perf_counter()
        data = encode()
        (tmp / name).write_bytes(data)
        return len(data), time.perf_counter() - t0

    jobs = small_files(phone, ar, parts, dev)  # the exporters looked up (native libraries loaded) on this thread
    here = {n: e for n, e in jobs.items() if FILES[n].device}
    threads = 1 if one_at_a_time else max(1, len(jobs) - len(here))
    with ThreadPoolExecutor(threads, thread_name_prefix="bonemesh-encode") as pool:
        if one_at_a_time:  # the device's exporters first, then the others in the one thread, one by one
            done = {n: made(n, e) for n, e in here.items()}
            beside = {n: pool.submit(made, n, e) for n, e in jobs.items() if n not in here}
        else:
            beside = {n: pool.submit(made, n, e) for n, e in jobs.items() if n not in here}
            done = {n: made(n, e) for n, e in here.items()}
        done.update({n: f.result() for n, f in beside.items()})
    return {n: done[n][0] for n in jobs}, {n: done[n][1] for n in jobs}


def _layout_device(recon: Reconstruction, dev: Any, budget: Budget, report: Report) -> tuple[Any, bool]:
    """Where the model is laid out for its files, and whether that is the host (``Budget.place``: past the budget
    of a GPU; ``report["layout"]`` says where and why)."""
    n_faces = len(recon.device_mesh[1]) if recon.device_mesh is not None else len(recon.mesh.faces)
    what = f"laying out the model ({n_faces:,} faces) for its files"
    where, note = budget.place(dev, budget.costs.layout_bytes(n_faces), what)
    report["layout"] = note or {"device": str(getattr(where, "label", where))}
    return where, note is not None


def _host_copies(where: Any, nbytes: int) -> Any:
    """``engine.staging.host_copies`` on a Warp device (pinned memory where it holds some); on another backend
    none (``lay_out`` copies plain)."""
    import contextlib

    import warp as wp

    from engine.staging import host_copies

    if isinstance(where, wp.Device):
        return host_copies(where, nbytes)
    return contextlib.nullcontext(None)
