"""The backend interface (``Backend``) and what host stages declare for it: named kernels (``Kernel``) and kernel
argument structs (``Struct``).

Arrays are the backend's own (a ``wp.array`` for Warp, an ``engine.backend.opencl_backend.CLArray`` for OpenCL);
host code never looks inside them, only at ``shape`` and ``len()``. Element types are numpy dtypes (``np.int32``,
``np.float32``, ``np.uint8``, ...) or the two vector types ``VEC3F`` and ``VEC3I`` (three packed 4-byte values:
Warp's ``vec3`` / ``vec3i``, ``float*`` / ``int*`` at ``3 * i`` in OpenCL C). Offsets and counts are in elements of
the array's type. Every call is ordered on the backend's one queue; ``to_host`` and the scans' totals wait for it.
"""

from __future__ import annotations

import abc
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

VEC3F = "vec3f"  # three float32, packed (12 bytes)
VEC3I = "vec3i"  # three int32, packed (12 bytes)
VEC10D = "vec10d"  # ten float64, packed (80 bytes): a quadric
VECTORS = {VEC3F: (3, np.float32), VEC3I: (3, np.int32), VEC10D: (10, np.float64)}  # components, component type
DType = Any  # a numpy dtype (or type) or VEC3F / VEC3I


def is_vector(dtype: DType) -> bool:
    """Whether ``dtype`` is one of the packed vector types."""
    return isinstance(dtype, str) and dtype in VECTORS


def components(dtype: DType) -> int:
    """Values per element: a vector type's length, else 1."""
    return VECTORS[dtype][0] if is_vector(dtype) else 1


def itemsize(dtype: DType) -> int:
    """Bytes of one element of ``dtype``."""
    if is_vector(dtype):
        n, t = VECTORS[dtype]
        return n * int(np.dtype(t).itemsize)
    return int(np.dtype(dtype).itemsize)


def host_dtype(dtype: DType) -> np.dtype[Any]:
    """The numpy scalar type of an element (the vector types' component type)."""
    if is_vector(dtype):
        return np.dtype(VECTORS[dtype][1])
    return np.dtype(dtype)


@dataclass(frozen=True)
class Kernel:
    """A named kernel, written once per backend: ``warp`` is ``"module:attribute"`` of a ``@wp.kernel``, ``opencl``
    is ``"package:file.cl:function"`` of an OpenCL C kernel. A kernel generic over the volume's sample type is
    launched with ``dtype=`` (Warp infers it from the arguments; the OpenCL program is built per type, with the
    type as ``VOL_T``)."""

    name: str
    warp: str
    opencl: str


@dataclass(frozen=True)
class Struct:
    """A kernel argument passed by value: ``warp`` is ``"module:attribute"`` of a ``@wp.struct``; ``fields`` are its
    ``(name, numpy type)`` in declaration order, the same order as the OpenCL C ``typedef struct`` (4-byte fields
    only, so the layouts match without padding)."""

    name: str
    warp: str
    fields: tuple[tuple[str, Any], ...]


COMPACT = Kernel(
    "backend.compact",
    warp="engine.backend.kernels.compact:compact_kernel",
    opencl="engine.backend.kernels:scan.cl:compact",
)  # the backends' own stream compaction (``Backend.compact``)


class PeakTracker(abc.ABC):
    """The most device memory a job had in use between ``start()`` and ``peak()``, beyond what was in use before
    (``how`` says how it was measured)."""

    how: str = "none"
    baseline: int = 0  # bytes in use when measuring started

    @abc.abstractmethod
    def start(self) -> PeakTracker: ...

    @abc.abstractmethod
    def peak(self) -> int | None: ...

    def stop(self) -> None:  # noqa: B027 - optional
        """Stop measuring."""


class Backend(abc.ABC):
    """What the host stages call on a device. ``kind`` is ``"warp"`` or ``"opencl"``; ``label`` names the device
    for reports; ``is_host`` is true where the device is the host's CPU."""

    kind: str
    label: str
    is_host: bool
    spec: str  # the concrete device spec it runs on: "cpu", "cuda:N" or "opencl:N" (reports, logs)

    # -- memory ---------------------------------------------------------------------------------------------------
    @abc.abstractmethod
    def empty(self, shape: int | tuple[int, ...], dtype: DType) -> Any:
        """An uninitialised device array."""

    @abc.abstractmethod
    def zeros(self, shape: int | tuple[int, ...], dtype: DType) -> Any:
        """A device array of zeros."""

    @abc.abstractmethod
    def full(self, shape: int | tuple[int, ...], value: float, dtype: DType) -> Any:
        """A device array filled with ``value``."""

    @abc.abstractmethod
    def fill(self, arr: Any, value: float) -> None:
        """Set every element of ``arr`` (scalar arrays) to ``value``."""

    @abc.abstractmethod
    def nbytes(self, arr: Any) -> int:
        """Device bytes ``arr``'s elements span (a view's too; Warp: 0 for a strided view)."""

    # -- copies ---------------------------------------------------------------------------------------------------
    @abc.abstractmethod
    def from_host(self, host: np.ndarray, dtype: DType | None = None) -> Any:
        """A new device array with ``host``'s values (``dtype`` a vector type for an (n, components) array)."""

    @abc.abstractmethod
    def upload(self, dst: Any, host: np.ndarray, dst_offset: int = 0) -> None:
        """Host to device: ``host``'s values into ``dst`` from element ``dst_offset``."""

    @abc.abstractmethod
    def to_host(self, arr: Any, count: int | None = None) -> np.ndarray:
        """Device to host (a sync point): the first ``count`` elements (all by default); vector arrays as
        (n, components)."""

    @abc.abstractmethod
    def download(self, dst: np.ndarray, src: Any, src_offset: int = 0) -> None:
        """Device to host into ``dst`` (C-contiguous, of ``src``'s type): ``dst.size`` elements of ``src`` from
        ``src_offset``. It may still run when this returns (where ``dst`` is page-locked): read ``dst``, or let
        anything else write it, only after ``synchronize()``."""

    @abc.abstractmethod
    def copy(self, dst: Any, src: Any, dst_offset: int = 0, src_offset: int = 0, count: int | None = None) -> None:
        """Device to device: ``count`` elements (all of ``src`` from ``src_offset`` by default)."""

    @abc.abstractmethod
    def view(self, arr: Any, lo: int, hi: int) -> Any:
        """Rows ``lo:hi`` of ``arr`` along its first axis, sharing memory where the device allows (else a copy)."""

    @abc.abstractmethod
    def clone(self, arr: Any) -> Any:
        """A new device array with ``arr``'s values."""

    # -- kernels --------------------------------------------------------------------------------------------------
    @abc.abstractmethod
    def struct(self, spec: Struct, **values: Any) -> Any:
        """A value of the kernel struct ``spec`` to pass to ``launch``."""

    @abc.abstractmethod
    def launch(self, kernel: Kernel, dim: int | tuple[int, ...], args: list[Any], dtype: DType | None = None) -> None:
        """Run ``kernel`` over ``dim`` threads with ``args`` (device arrays, Python ints and floats as 32-bit,
        ``struct`` values); ``dtype`` picks the variant of a kernel generic over the volume's sample type."""

    @abc.abstractmethod
    def scalar(self, value: float, dtype: DType) -> Any:
        """A kernel argument of type ``dtype`` (``np.float64``, ``np.int64``: Python numbers pass as 32-bit)."""

    @abc.abstractmethod
    def vector(self, values: Any, dtype: DType) -> Any:
        """Three values as one kernel argument passed by value: ``np.float32`` (Warp's ``vec3``; OpenCL C: a struct
        of three floats) or ``np.float64`` (``vec3d``; OpenCL C: ``origin_t``, three doubles)."""

    @abc.abstractmethod
    def prepared(self, kernel: Kernel, dim: int, args: list[Any]) -> Callable[[], None]:
        """A launch whose arguments are packed once, run by calling it (packing a short kernel's arguments costs
        more than its launch: Warp records the command)."""

    @abc.abstractmethod
    def exclusive_scan(self, src: Any, dst: Any) -> int:
        """``dst[i] = sum(src[:i])`` over int32 arrays; returns the total (a sync point)."""

    @abc.abstractmethod
    def prefix_sum(self, src: Any, dst: Any) -> None:
        """``exclusive_scan`` without reading the total back (no sync point)."""

    @abc.abstractmethod
    def sort_pairs(self, keys: Any, values: Any, n: int) -> None:
        """Sort the first ``n`` int64 ``keys`` and their int32 ``values`` by key, stably (equal keys keep their
        order), in place; both arrays hold at least ``2 n`` elements (room a radix sort may work in)."""

    @abc.abstractmethod
    def compact(self, flags: Any) -> tuple[Any, Any, int]:
        """Stream compaction of an int32 array of 0/1: ``(indices, ranks, n)`` where ``indices[:n]`` are the flagged
        positions in order (at least one element allocated) and ``ranks[i]`` is position ``i``'s place in it, or -1
        (a sync point)."""

    @abc.abstractmethod
    def synchronize(self) -> None:
        """Wait for everything queued."""

    # -- budget ---------------------------------------------------------------------------------------------------
    @abc.abstractmethod
    def peak_tracker(self) -> PeakTracker:
        """A tracker of this device's memory high-water mark."""

    @abc.abstractmethod
    def default_budget(self) -> int:
        """Bytes a stage's working set may use by default."""

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.label}>"


def host_budget() -> int:
    """A quarter of the host's available memory: the default working set of a stage on the CPU."""
    try:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        avail = 8 << 30
    return int(avail * 0.25)
