"""The EMC33 pipeline: volume in, mesh and report out (``reconstruct``); the output files are ``engine.job.outputs``'.

Stages, in order (``STAGES``): preprocess (host: optional crop and slice filters, then the body mask of
``engine.volume.bodymask`` for HU data), upload (the volume, once), gaussian, isosurface (MC33), decimate
(quadric edge collapse), islands (optional, on the decimated mesh), smooth (surface-preserving Laplacian), normals.
``reconstruct`` chooses its plan once from the memory budget (``engine.job.plans``: the whole volume at once, or
streamed in slabs within the budget) and runs its stages in order; everything after preprocess runs on the device
where the data already is, and only the finished mesh comes back. A failing stage raises ``StageError`` naming it
(or the raw error with ``BONEMESH_DEBUG=1``); bad input raises ``InputError``.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from engine.budget import Budget, BudgetSpec
from engine.errors import EmptySurfaceError, InputError, StageError
from engine.job.plans import STAGES, Stage, State, join_warnings, out_of_core, plan_for
from engine.job.progress import StageProgress
from engine.params import ReconParams
from engine.report import Report
from engine.types import Mesh, Volume

if TYPE_CHECKING:
    from engine.device import DeviceSpec

__all__ = ["STAGES", "EmptySurfaceError", "OnProgress", "Reconstruction", "StageError", "reconstruct"]

OnProgress = Callable[[str, float], None]


class Reconstruction:
    """The result: the final mesh (with normals) and a JSON-able report (``engine.report.Report``).

    ``reconstruct`` leaves the mesh on its device (``device_mesh``: positions, faces, normals as Warp arrays, which
    ``write_outputs`` lays out there); ``mesh`` brings it to the host on first use.
    """

    def __init__(
        self, mesh: Mesh | None = None, report: Report | None = None, device_mesh: Any = None, defect: Any = None
    ):
        if mesh is None and device_mesh is None:
            raise ValueError("a Reconstruction needs a mesh or a device mesh")
        self._mesh = mesh
        self.defect = defect  # engine.defect.step.DefectOutcome when ReconParams.defect asked for it
        # a mesh made elsewhere has no pipeline blocks yet: write_outputs adds its own to an empty report
        self.report: Report = cast(Report, {}) if report is None else report
        self.device_mesh = device_mesh

    @property
    def mesh(self) -> Mesh:
        if self._mesh is None:
            from engine.backend.select import backend_of

            pos, faces, normals = self.device_mesh  # sync point: the finished mesh comes back
            be = backend_of(pos)
            self._mesh = Mesh(
                be.to_host(pos).astype(np.float32).reshape(-1, 3),
                be.to_host(faces).astype(np.int32).reshape(-1, 3),
                be.to_host(normals).astype(np.float32).reshape(-1, 3),
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


def reconstruct(
    volume: Volume,
    params: ReconParams | None = None,
    *,
    device: DeviceSpec = "auto",
    on_progress: OnProgress | None = None,
    max_device_bytes: BudgetSpec = None,
) -> Reconstruction:
    """Run the EMC33 pipeline on a volume.

    Args:
        volume: the scan (see ``engine.types.Volume``).
        params: pipeline parameters (defaults: the paper's best combination).
        device: "auto", "cpu", "cuda" or "cuda:N", "opencl" or "opencl:N" (``engine.backend``: every stage on
            OpenCL), a Warp device, or a ``Backend`` (``engine.job.Runtime.backend``: resolved already;
            ``engine.device.resolve_device``, ``resolve_backend``); or several devices of one kind, "cuda:0,cuda:1",
            "cuda:all" or their backends (``engine.job.Runtime.device``): the volume is split in z over them, each
            part streamed and decimated in groups on its own device with the budget (its default where none is
            given), then joined and finished on the first (``engine.isosurface.multi``, docs/multi-gpu.md).
        on_progress: called as ``on_progress(stage, fraction_done)`` when a stage starts and ends and inside long
            stages (the decimation's passes); the fraction weights stages by their expected time
            (``engine.job.progress``).
        max_device_bytes: a device memory budget (bytes, text such as ``"2GiB"``, or an ``engine.budget.Budget``,
            parsed once by ``Budget.of``) that every stage keeps to (the ``STREAMED`` plan of ``engine.job.plans``):
            the volume is streamed in z slabs through the Gaussian and MC33, and a mesh whose decimation does not
            fit is decimated in groups of slabs and then in z tiles with pinned borders (``engine.isosurface.stream``,
            ``engine.decimation.tiles``). The volume stages' result is the same as without a budget; the decimation
            keeps the same topology and guards. ``None``: no budget (the ``WHOLE_VOLUME`` plan: the volume goes up
            at once). The peak used is reported in ``report["memory"]``. A ``Budget`` with a host memory bound
            (``Budget.host_bytes``): on a device whose memory is the host's the device budget comes out of it
            (``Budget.for_device``).

    ``volume.data`` may be a scan read slab by slab from disk (``engine.io.slabs.open_slabs``, under a host memory
    bound): the streamed plan then reads its slabs as the device stages need them (with the backend's default
    device budget where none is given), and the mesh is the same as from the loaded scan under the same device
    budget. The steps that need the whole scan in memory (slice preprocessing, the body mask's labelling on HU
    data, the defect) are refused with the option that avoids them.

    Returns:
        The final mesh (vertices (z, y, x) mm in the grid, outward faces, unit vertex normals) and the report; the
        report's ``frame`` maps the grid to the patient frame (``engine.orient``, applied by ``write_outputs``).

    Raises:
        InputError: the volume or parameters cannot give a model (EmptySurfaceError: no surface at the level;
            BudgetError: the memory budget or the host bound is too small, with the smallest that would work).
        StageError: a stage failed otherwise.
    """
    from engine.device import resolve_backends, resolve_device

    params = params or ReconParams()
    devices = resolve_backends(device)  # one; or a job over several devices (engine.isosurface.multi)
    be = devices[0]  # where the device stages run (the first device of several: all but the streamed stages)
    dev = resolve_device(be)  # Warp's device: the scope of Warp's stages (Warp's CPU for an OpenCL spec)
    budget = Budget.of(max_device_bytes).for_device(be)
    if len(devices) > 1 and not budget.limited and params.decimate is not None:  # several: the volume streams
        budget = budget.with_bytes(int(min(d.default_budget() for d in devices)))
    if out_of_core(volume):
        budget = _out_of_core_budget(volume, params, budget, be)
    report = _report_head(volume, params, device, dev, be)
    if len(devices) > 1:
        report["device"]["devices"] = [d.spec for d in devices]
    st = State(volume, budget, backend=be, devices=devices if len(devices) > 1 else ())
    with _host_bound_errors(budget, be):
        _run_plan(st, plan_for(budget), params, report, StageProgress(STAGES, on_progress), dev)
    if budget.host_bytes is not None:
        report["memory"]["host_bound_bytes"] = budget.host_bytes
        report["memory"]["out_of_core"] = out_of_core(volume)
    defect = _defect_step(st, params, report, dev)
    report["total_seconds"] = sum(report["stage_seconds"].values())
    return Reconstruction(report=report, device_mesh=(st.pos, st.faces, st.normals), defect=defect)


def _out_of_core_budget(volume: Volume, params: ReconParams, budget: Budget, be: Any) -> Budget:
    """The budget of a scan read slab by slab: a device budget (the backend's default where none is given), and a
    host bound that holds one read of the scan's planes.

    Raises:
        InputError: the defect is asked for (it needs the whole scan); BudgetError: the host bound cannot hold one
            read of planes (the smallest bound that can).
    """
    from engine.errors import BudgetError
    from engine.job.plans import refuse_out_of_core

    if params.defect is not None:
        refuse_out_of_core(volume, "the defect and its template", "leave --defect out")
    data = volume.data
    if budget.host_bytes is not None:
        plane = data.shape[1] * data.shape[2] * data.itemsize
        planes = max(int(getattr(data, "granule", 1)), 2)
        need = _rounded_up(int(planes * plane / budget.host_read_share))
        if budget.host_bytes < need:
            raise BudgetError(
                f"the host memory bound of {_size(budget.host_bytes)} cannot hold one read of this scan's planes "
                f"({planes} of {_size(plane)} at a time, in {budget.host_read_share:g} of the bound): give at least "
                f"{_size(need)}",
                needed=need,
            )
    if not budget.limited:
        budget = budget.with_bytes(int(be.default_budget()))
    return budget


def _rounded_up(n: int) -> int:
    """``n`` bytes rounded up to whole MiB (whole KiB under 1 MiB), for a bound that works."""
    unit = 1 << 20 if n >= 1 << 20 else 1 << 10
    return -(-n // unit) * unit


def _size(n: int) -> str:
    """A byte count for messages: MiB (``engine.budget.mib``), or KiB under 1 MiB."""
    from engine.budget import mib

    return mib(n) if n >= 1 << 20 else f"{n / 1024:,.0f} KiB"


@contextmanager
def _host_bound_errors(budget: Budget, be: Any) -> Iterator[None]:
    """A device ``BudgetError`` restated for the host bound where the device budget came out of it (a host
    device): the host bound that would give the device budget needed."""
    from engine.errors import BudgetError

    try:
        yield
    except BudgetError as exc:
        host = budget.host_bytes
        if host is None or not getattr(be, "is_host", False) or budget.bytes != int(host * budget.host_device_share):
            raise
        needed = _rounded_up(int(exc.needed / budget.host_device_share))
        raise BudgetError(
            f"{exc}; on this device the device budget is {budget.host_device_share:g} of the host memory bound of "
            f"{_size(host)}: give a --max-host-bytes of at least {_size(needed)}",
            needed=needed,
        ) from None


def _report_head(volume: Volume, params: ReconParams, device: Any, dev: Any, be: Any) -> Report:
    """The report's blocks known before any stage runs: parameters, device, versions, input."""
    return {
        "parameters": params.to_dict(),
        "device": {
            "spec": device if isinstance(device, str) else _spec_of(device),
            "name": str(dev) if be.kind == "warp" else be.label,
            "description": getattr(dev, "name", str(dev)) if be.kind == "warp" else be.label,
            "backend": be.kind,
        },
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


def _spec_of(device: Any) -> str:
    """A resolved device (a backend, a Warp device, or several backends) as its spec for the report."""
    if isinstance(device, (list, tuple)):
        return ",".join(_spec_of(d) for d in device)
    return str(getattr(device, "spec", device))


def _run_plan(
    st: State, plan: tuple[tuple[str, Stage], ...], params: ReconParams, report: Report, progress: Any, dev: Any
) -> None:
    """Run the plan's stages in order in Warp's scope of ``dev`` (each stage's failure named: ``StageError``),
    then the mesh's measures and the memory used into the report."""
    import warp as wp

    memory = st.backend.peak_tracker()
    with wp.ScopedDevice(dev):
        memory.start()
        for name, stage in plan:

            def within(fraction: float, name: str = name) -> None:
                progress.within(name, fraction)

            progress.start(name)
            t0 = time.perf_counter()
            try:
                with wp.ScopedDevice(_warp_device(st.pos, dev)):  # the host, past the budget
                    stage(st, params, report, within)
            except (InputError, StageError):
                raise
            except Exception as exc:
                if os.environ.get("BONEMESH_DEBUG") == "1":
                    raise
                raise StageError(name, exc) from exc
            report["stage_seconds"][name] = time.perf_counter() - t0
            progress.end(name)
        t0 = time.perf_counter()
        from engine.surface.devmesh import mesh_stats_device

        with wp.ScopedDevice(_warp_device(st.pos, dev)):  # sync point: the counts come back
            report["mesh"] = mesh_stats_device(st.pos, st.faces, st.incidence_built())
        join_warnings(st, report)
        report["finish_seconds"] = time.perf_counter() - t0
        report["memory"] = {
            "budget_bytes": st.budget.bytes,
            "peak_bytes": memory.peak(),
            "measured_by": memory.how,
            "in_use_before_bytes": memory.baseline,
        }
        memory.stop()
        if st.stream is not None:
            report["memory"]["stream"] = st.stream.info


def _warp_device(arr: Any, dev: Any) -> Any:
    """The Warp device a stage runs in: that of ``arr`` where it is a Warp array (the host, past the budget), else
    ``dev`` (an OpenCL array's stages need no Warp scope; Warp's CPU device then)."""
    import warp as wp

    return arr.device if isinstance(arr, wp.array) else dev


def _defect_step(st: State, params: ReconParams, report: Report, dev: Any) -> Any:
    """The defect and its template (``engine.defect.step``) on the scan as the model saw it (cropped, bone inside
    the body), at the model's level, when ``params.defect`` asks; None otherwise."""
    if params.defect is None:
        return None
    from engine.defect.step import find_defect, measured_on

    t0 = time.perf_counter()
    on = measured_on(params.orient, dict(report["iso_level"]), report.get("body_mask"))
    try:
        outcome = find_defect(st.volume, params.defect, st.level, st.backend, params.orient, on)
    except InputError:
        raise
    except Exception as exc:
        if os.environ.get("BONEMESH_DEBUG") == "1":
            raise
        raise StageError("defect", exc) from exc
    report["stage_seconds"]["defect"] = time.perf_counter() - t0
    report["defect"] = outcome.summary()
    return outcome
