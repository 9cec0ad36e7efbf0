"""Where a job runs, resolved once at its edge (the CLI's flags, the worker's settings): ``Runtime`` holds the
backend the device stages run on, Warp's device for Warp's own steps, the memory budget and how slices are decoded.
Everything below the edge takes it (or its ``backend``) and never resolves a device spec again.

``auto`` is resolved here once, with the reason (``Runtime.reason``), so a worker logs what it chose and its
warm-up (``engine.job.warmup.warm_up``) warms the very backend its jobs use.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from engine.budget import Budget, BudgetSpec

if TYPE_CHECKING:
    from engine.backend.base import Backend
    from engine.io.png_rows import DeviceRows
    from engine.staging import VolumeBuffer

__all__ = ["PNG_DECODERS", "Runtime", "resolve_runtime"]

PNG_DECODERS = ("auto", "libpng", "pillow")


@dataclass(frozen=True)
class Runtime:
    """A job's device and budgets, resolved (``resolve_runtime``).

    Attributes:
        backend: where the device stages run (``engine.backend.Backend``: Warp on a CUDA device or the CPU, or
            OpenCL); pass it as ``device=`` to any engine function.
        warp_device: Warp's device for Warp's own steps (Warp's CPU where the backend is OpenCL).
        requested: the spec asked for ("auto", "cuda:1", ...); ``backend.spec`` is what it resolved to.
        reason: why ``auto`` chose this device (empty for an explicit spec).
        budget: the device memory budget every stage keeps to, and the host memory bound (``engine.budget``: on a
            host device the device budget comes out of the host bound).
        png_decoder: ``auto`` (PNG rows unfiltered on a GPU), ``libpng`` or ``pillow``.
        decode_threads, decode_processes: how slices are decoded (``engine.io.load_volume``; None: its default).
        devices: a job over several devices ("cuda:0,cuda:1", "cuda:all"): their backends, ``backend`` the first
            (empty for one device): the model's volume stages are split over them (``engine.isosurface.multi``).
    """

    backend: Backend
    warp_device: Any
    requested: str
    reason: str
    budget: Budget
    png_decoder: str = "auto"
    decode_threads: int | None = None
    decode_processes: bool | None = None
    devices: tuple[Backend, ...] = ()

    @property
    def spec(self) -> str:
        """The concrete device spec: "cpu", "cuda:N" or "opencl:N" (of several: "cuda:0,cuda:1")."""
        return ",".join(be.spec for be in self.devices) if self.devices else self.backend.spec

    @property
    def device(self) -> Backend | tuple[Backend, ...]:
        """What ``engine.reconstruct`` takes as its ``device``: the backend, or the backends of several devices."""
        return self.devices or self.backend

    def rows(self) -> DeviceRows | None:
        """PNG slices' rows unfiltered on this device where it is a GPU and ``png_decoder`` is ``auto``
        (``engine.io.png_rows.device_rows``), else None."""
        from engine.io.png_rows import device_rows

        return device_rows(self.backend) if self.png_decoder == "auto" else None

    def volumes(self) -> VolumeBuffer | None:
        """The process's page-locked buffer loads decode into on a CUDA device (``engine.staging``), else None."""
        from engine.staging import pinned_volumes

        return pinned_volumes(self.backend)

    def describe(self) -> str:
        """One line for a log: what runs where, and why."""
        why = f" ({self.reason})" if self.reason else ""
        budget = f", budget {self.budget.bytes:,} bytes" if self.budget.bytes is not None else ""
        if self.budget.host_bytes is not None:
            budget += f", host bound {self.budget.host_bytes:,} bytes"
        label = " + ".join(be.label for be in self.devices) if self.devices else self.backend.label
        return f"device {self.requested} -> {label}{why}{budget}"


def resolve_runtime(
    device: Any = "auto",
    max_device_bytes: BudgetSpec = None,
    *,
    png_decoder: str = "auto",
    decode_threads: int | None = None,
    decode_processes: bool | None = None,
    max_host_bytes: str | int | None = None,
) -> Runtime:
    """Resolve a device spec (``engine.device``: "auto", "cpu", "cuda[:N]", "opencl[:N]", a Warp device or a
    ``Backend``; or several devices of one kind: "cuda:0,cuda:1", "cuda:all", ``engine.device.resolve_backends``) and
    a budget once: the device budget ``max_device_bytes`` and the host memory bound
    ``max_host_bytes`` (``"64GiB"``, bytes, None: none; ``Budget.with_host``, ``Budget.for_device``).

    Raises:
        ValueError: a malformed spec, a device (or PyOpenCL, or an OpenCL driver) that is not present, a budget or
            a decoder that is not one, a list that mixes backends.
    """
    from engine.backend.select import auto_spec, get_backend
    from engine.device import is_device_list, resolve_backends, resolve_device

    if png_decoder not in PNG_DECODERS:
        raise ValueError(f"png_decoder must be one of {', '.join(PNG_DECODERS)}, got {png_decoder!r}")
    requested = device if isinstance(device, str) else str(getattr(device, "spec", device))
    reason = ""
    devices: tuple[Backend, ...] = ()
    if is_device_list(device):
        devices = resolve_backends(device)
        requested = device if isinstance(device, str) else ",".join(be.spec for be in devices)
        device = devices[0]
        devices = devices if len(devices) > 1 else ()  # one device ("cuda:all" on a host of one): as it names
    if device == "auto":
        device = auto_spec()
        reason = _auto_reason(device)
    backend = get_backend(device)
    return Runtime(
        backend=backend,
        warp_device=resolve_device(backend),
        requested=requested,
        reason=reason,
        budget=_budget(max_device_bytes, max_host_bytes).for_device(backend),
        png_decoder=png_decoder,
        decode_threads=decode_threads,
        decode_processes=decode_processes,
        devices=devices,
    )


def _budget(device: BudgetSpec, host: str | int | None) -> Budget:
    """The device budget with the host bound (a ``Budget`` given keeps its own bound unless ``host`` is given)."""
    budget = Budget.of(device)
    return budget if host is None else budget.with_host(host)


def _auto_reason(spec: str) -> str:
    """Why ``auto`` meant ``spec`` (``engine.backend.select.auto_spec``'s order), and why CUDA was passed over where
    an NVIDIA driver is loaded (a driver too old for Warp's CUDA build, say: loud, not a quiet CPU run)."""
    if spec.startswith("cuda"):
        return "auto: a CUDA GPU is present"
    from engine.backend.warp_device import cuda_problem

    nvidia, why = cuda_problem()
    unusable = f"; an NVIDIA driver is loaded but CUDA is unusable: {why}" if nvidia and why else ""
    if spec.startswith("opencl"):
        from engine.backend.select import get_backend

        if not get_backend(spec).is_host:
            return f"auto: no CUDA GPU; an OpenCL GPU is present{unusable}"
        return f"auto: no GPU; OpenCL on the CPU (every core) is the faster CPU path{unusable}"
    return (
        "auto: no GPU and no OpenCL driver; Warp's CPU path (one thread; install pocl-opencl-icd and "
        f"bonemesh[opencl] for every core){unusable}"
    )
