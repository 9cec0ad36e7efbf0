"""Device specs ("auto", "cpu", "cuda", "cuda:N", "opencl", "opencl:N") as the engine's functions accept them:
``resolve_backend`` (the backend the device stages run on, ``engine.backend.select.get_backend``) and
``resolve_device`` (the Warp device of Warp's own steps: Warp's CPU where the stages run on OpenCL).

A job resolves its spec once, at its edge, into an ``engine.job.Runtime`` and passes its ``Backend`` down; both
functions return what a ``Backend`` (or a Warp device) already names without looking anything up again. The layers
below this module (``engine.backend.warp_device``, ``engine.backend.select``) never import it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, TypeAlias

from engine.backend.warp_device import cuda_available, init_runtime

if TYPE_CHECKING:  # pragma: no cover
    import warp as wp

    from engine.backend.base import Backend

__all__ = [
    "DeviceSpec",
    "cuda_available",
    "device_list",
    "init_runtime",
    "is_device_list",
    "resolve_backend",
    "resolve_backends",
    "resolve_device",
]

# "auto", "cpu", "cuda", "cuda:N", "opencl", "opencl:N", a Warp device, or a Backend (resolved already); a job over
# several devices: "cuda:0,cuda:1", "cuda:all", or their backends (``resolve_backends``)
DeviceSpec: TypeAlias = "str | wp.Device | Backend | tuple[Backend, ...]"


def resolve_device(spec: Any = "auto") -> wp.Device:
    """Return the Warp device for ``spec``.

    Args:
        spec: "auto" (``engine.backend.select.auto_spec``: CUDA when present, else an OpenCL GPU, else the faster
            CPU path; Warp's CPU device where the stages run on OpenCL), "cpu", "cuda" or "cuda:N", a Warp device
            (returned as is), a ``Backend`` (its Warp device; Warp's CPU for an OpenCL one), or "opencl" /
            "opencl:N" (N counts every OpenCL device of every platform, GPUs first, then accelerators, then CPUs:
            ``engine.backend.opencl_devices``), checked to be present, which gives Warp's CPU device.

    Raises:
        ValueError: the spec is malformed or names a CUDA device that is not present; for "opencl[:N]", PyOpenCL,
            any OpenCL platform or device N is missing.
    """
    from engine.backend.select import get_backend

    device: wp.Device = _warp_device_of(get_backend(spec))
    return device


def _warp_device_of(backend: Backend) -> Any:
    """A Warp backend's device; Warp's CPU device for another backend (Warp's own steps beside OpenCL)."""
    if backend.kind == "warp":
        return backend.device  # type: ignore[attr-defined]
    from engine.backend.warp_device import warp_device

    return warp_device("cpu")


def resolve_backend(spec: Any = "auto") -> Backend:
    """The backend (``engine.backend.Backend``) the device stages run on for ``spec``: OpenCL for "opencl[:N]",
    else Warp on ``resolve_device(spec)``'s device (a backend is returned as is).

    Raises:
        ValueError: as ``resolve_device``.
    """
    from engine.backend.select import get_backend

    return get_backend(spec)


def is_device_list(spec: Any) -> bool:
    """Whether ``spec`` names several devices: a comma list (``"cuda:0,cuda:1"``), ``"cuda:all"``, or a list or
    tuple of specs or backends."""
    if isinstance(spec, str):
        return "," in spec or spec.strip() == "cuda:all"
    return isinstance(spec, (list, tuple))


def device_list(spec: str) -> list[str]:
    """The device specs of a list spec, in order: ``"cuda:0,cuda:1"`` (a device may be named twice: its parts then
    run in turn, as tests do with ``"cpu,cpu"``), or ``"cuda:all"``, every CUDA device Warp sees.

    Raises:
        ValueError: an empty item, an item that is not a device spec (``auto`` and ``cuda:all`` inside a list
            included), or ``cuda:all`` where no CUDA device is present.
    """
    from engine.backend.select import SPEC

    if spec.strip() == "cuda:all":
        from engine.backend.warp_device import cuda_problem

        if not cuda_available():
            why = cuda_problem()[1]
            raise ValueError(f"device 'cuda:all': no CUDA device is present{': ' + why if why else ''}")
        import warp as wp

        return [f"cuda:{i}" for i in range(wp.get_cuda_device_count())]
    items = [item.strip() for item in spec.split(",")]
    for item in items:
        if not item or not SPEC.match(item) or item == "auto":
            raise ValueError(
                f"Expected a list of devices such as 'cuda:0,cuda:1' (each cpu, cuda[:N] or opencl[:N]; or "
                f"'cuda:all'), got {item!r} in {spec!r}"
            )
    return items


def resolve_backends(spec: Any = "auto") -> tuple[Backend, ...]:
    """The backends of a device spec: one for a single device (``resolve_backend``), in order for a list
    (``device_list``; a list or tuple of specs or backends). The devices of a list share one job (its volume split
    over them in z: ``engine.isosurface.multi``), so they must run the same kernels at comparable speeds.

    Raises:
        ValueError: as ``resolve_backend`` for any device of the list (naming it), or a list that mixes backends
            (Warp and OpenCL) or the host's CPU with GPUs.
    """
    if not is_device_list(spec):
        return (resolve_backend(spec),)
    items = device_list(spec) if isinstance(spec, str) else list(spec)
    backends = []
    for item in items:
        try:
            backends.append(resolve_backend(item))
        except ValueError as exc:
            raise ValueError(f"device {item!r} of the list {_named(spec)}: {exc}") from None
    kinds = {be.kind for be in backends}
    if len(kinds) > 1:
        raise ValueError(
            f"the devices {_named(spec)} mix backends ({', '.join(sorted(kinds))}): one job's parts run the same "
            "kernels and are joined on its first device; list CUDA devices (cuda:N) or OpenCL devices (opencl:N), "
            "not both"
        )
    if len({be.is_host for be in backends}) > 1:
        raise ValueError(
            f"the devices {_named(spec)} mix the host's CPU with GPUs: the job waits for its slowest part, and a "
            "CPU part would take far longer than a GPU's; list GPUs only"
        )
    return tuple(backends)


def _named(spec: Any) -> str:
    """A device list for messages."""
    if isinstance(spec, str):
        return repr(spec)
    return repr(",".join(str(getattr(item, "spec", item)) for item in spec))
