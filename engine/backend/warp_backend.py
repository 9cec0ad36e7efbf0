"""The Warp backend: what the engine did before the interface, behind it (a CUDA device or Warp's CPU path)."""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable
from typing import Any

import numpy as np

from engine.backend.base import (
    COMPACT,
    VEC3F,
    VEC3I,
    VEC10D,
    Backend,
    DType,
    Kernel,
    PeakTracker,
    Struct,
    components,
    is_vector,
)


@functools.cache
def _resolve(where: str) -> Any:
    module, _, attr = where.partition(":")
    return getattr(importlib.import_module(module), attr)


def _wp_dtype(dtype: DType) -> Any:
    import warp as wp

    if dtype == VEC3F:
        return wp.vec3
    if dtype == VEC3I:
        return wp.vec3i
    if dtype == VEC10D:
        from engine.backend.kernels.vectors import vec10d

        return vec10d
    return wp.dtype_from_numpy(np.dtype(dtype))


class _WarpPeak(PeakTracker):
    """``engine.backend.memory.PeakMemory`` (the CUDA pool's high-water mark, or Warp's allocation tracker on the
    CPU)."""

    def __init__(self, device: Any) -> None:
        from engine.backend.memory import PeakMemory

        self._peak = PeakMemory(device)

    def start(self) -> PeakTracker:
        self._peak.start()
        self.how, self.baseline = self._peak.how, self._peak.baseline
        return self

    def peak(self) -> int | None:
        return self._peak.peak()

    def stop(self) -> None:
        self._peak.stop()


class WarpBackend(Backend):
    """Warp on ``device`` (a ``wp.Device``); every call names the device (no ``wp.ScopedDevice`` needed)."""

    kind = "warp"

    def __init__(self, device: Any) -> None:
        self.device = device
        self.label = f"warp {device}"
        self.spec = str(device)
        self.is_host = not device.is_cuda

    def empty(self, shape: int | tuple[int, ...], dtype: DType) -> Any:
        import warp as wp

        return wp.empty(shape, dtype=_wp_dtype(dtype), device=self.device)

    def zeros(self, shape: int | tuple[int, ...], dtype: DType) -> Any:
        import warp as wp

        return wp.zeros(shape, dtype=_wp_dtype(dtype), device=self.device)

    def full(self, shape: int | tuple[int, ...], value: float, dtype: DType) -> Any:
        import warp as wp

        return wp.full(shape, value, dtype=_wp_dtype(dtype), device=self.device)

    def fill(self, arr: Any, value: float) -> None:
        arr.fill_(value)

    def nbytes(self, arr: Any) -> int:
        return int(arr.capacity) if arr.is_contiguous else 0

    def from_host(self, host: np.ndarray, dtype: DType | None = None) -> Any:
        import warp as wp

        host = np.ascontiguousarray(host)
        if is_vector(dtype):
            return wp.array(host.reshape(-1, components(dtype)), dtype=_wp_dtype(dtype), device=self.device)
        return wp.array(host, device=self.device)

    def upload(self, dst: Any, host: np.ndarray, dst_offset: int = 0) -> None:
        import warp as wp

        src: Any = wp.array(np.ascontiguousarray(host), dtype=dst.dtype, device="cpu")
        wp.copy(dst, src, dest_offset=dst_offset, count=src.size)

    def to_host(self, arr: Any, count: int | None = None) -> np.ndarray:
        out: np.ndarray = (arr if count is None else arr[:count]).numpy()
        return out

    def download(self, dst: np.ndarray, src: Any, src_offset: int = 0) -> None:
        import warp as wp

        if dst.size:  # wraps ``dst`` (no copy); CUDA copies into page-locked memory asynchronously
            host: Any = wp.array(dst.reshape(-1), dtype=src.dtype, device="cpu", copy=False)
            wp.copy(host, src, src_offset=src_offset, count=dst.size)

    def copy(self, dst: Any, src: Any, dst_offset: int = 0, src_offset: int = 0, count: int | None = None) -> None:
        import warp as wp

        n = src.size - src_offset if count is None else count
        wp.copy(dst, src, dest_offset=dst_offset, src_offset=src_offset, count=n)

    def view(self, arr: Any, lo: int, hi: int) -> Any:
        return arr[lo:hi]

    def clone(self, arr: Any) -> Any:
        import warp as wp

        return wp.clone(arr)

    def scalar(self, value: float, dtype: DType) -> Any:
        return _wp_dtype(dtype)(value)

    def vector(self, values: Any, dtype: DType) -> Any:
        import warp as wp

        x, y, z = (float(v) for v in values)
        return wp.vec3d(x, y, z) if np.dtype(dtype) == np.float64 else wp.vec3(x, y, z)

    def prepared(self, kernel: Kernel, dim: int, args: list[Any]) -> Callable[[], None]:
        import warp as wp

        cmd = wp.launch(_resolve(kernel.warp), dim=dim, inputs=args, device=self.device, record_cmd=True)
        return cmd.launch  # type: ignore[no-any-return]

    def struct(self, spec: Struct, **values: Any) -> Any:
        s = _resolve(spec.warp)()
        for name, _ in spec.fields:
            setattr(s, name, values[name])
        return s

    def launch(self, kernel: Kernel, dim: int | tuple[int, ...], args: list[Any], dtype: DType | None = None) -> None:
        import warp as wp

        wp.launch(_resolve(kernel.warp), dim=dim, inputs=args, device=self.device)

    def exclusive_scan(self, src: Any, dst: Any) -> int:
        import warp as wp

        n = len(src)
        if n == 0:
            return 0
        wp.utils.array_scan(src, dst, inclusive=False)
        return int(dst[n - 1 : n].numpy()[0] + src[n - 1 : n].numpy()[0])  # sync point

    def prefix_sum(self, src: Any, dst: Any) -> None:
        import warp as wp

        if len(src):
            wp.utils.array_scan(src, dst, inclusive=False)

    def sort_pairs(self, keys: Any, values: Any, n: int) -> None:
        import warp as wp

        if n:
            wp.utils.radix_sort_pairs(keys, values, n)

    def compact(self, flags: Any) -> tuple[Any, Any, int]:
        import warp as wp

        pos = wp.empty(len(flags), dtype=wp.int32, device=self.device)
        n = self.exclusive_scan(flags, pos)
        indices = wp.empty(max(n, 1), dtype=wp.int32, device=self.device)
        ranks = wp.empty(len(flags), dtype=wp.int32, device=self.device)
        if len(flags):
            self.launch(COMPACT, len(flags), [flags, pos, indices, ranks])
        return indices, ranks, n

    def synchronize(self) -> None:
        import warp as wp

        wp.synchronize_device(self.device)

    def peak_tracker(self) -> PeakTracker:
        return _WarpPeak(self.device)

    def default_budget(self) -> int:
        from engine.backend.base import host_budget

        if self.device.is_cuda:
            return int(self.device.free_memory * 0.5)
        return host_budget()
