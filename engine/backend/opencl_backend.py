"""The OpenCL backend through PyOpenCL: one context and in-order queue per device, programs built once per context
(and per volume sample type), PoCL on the CPU or any GPU platform.

Kernels are OpenCL C files beside each stage's Warp kernels (``engine/<package>/kernels/*.cl``), written to give the
same bits as Warp's: ``#pragma OPENCL FP_CONTRACT OFF`` in every file (no fused multiply-adds Warp does not make),
``f``-suffixed literals, and ``-cl-fp32-correctly-rounded-divide-sqrt`` where the device offers it (GPUs divide to
2.5 ulp by default). A kernel over Warp's ``dim=(a, b, c)`` (``z, y, x = wp.tid()``) runs over OpenCL's global size
``(c, b, a)``: id 0 is the fastest axis.
"""

from __future__ import annotations

import importlib.resources
import re
import threading
import warnings
import weakref
from collections.abc import Callable
from typing import Any

import numpy as np

from engine.backend.base import (
    COMPACT,
    Backend,
    DType,
    Kernel,
    PeakTracker,
    Struct,
    components,
    host_budget,
    host_dtype,
    is_vector,
    itemsize,
)

SCAN_CHUNKS = 4096  # runs of an exclusive scan (each summed and scanned by one work item)
_SCAN = "engine.backend.kernels:scan.cl"
_SCAN_SUMS = Kernel("backend.scan.sums", "", f"{_SCAN}:chunk_sums")
_SCAN_TOP = Kernel("backend.scan.top", "", f"{_SCAN}:scan_sums")
_SCAN_RUNS = Kernel("backend.scan.runs", "", f"{_SCAN}:chunk_scan")
_RADIX = "engine.backend.kernels:radix.cl"
_RADIX_RANGE = Kernel("backend.radix.range", "", f"{_RADIX}:chunk_range")
_RADIX_DIGITS = Kernel("backend.radix.digits", "", f"{_RADIX}:chunk_digits")
_RADIX_SCATTER = Kernel("backend.radix.scatter", "", f"{_RADIX}:chunk_scatter")
RADIX_BITS = 4  # a pass sorts by this many bits (radix.cl's RADIX = 2 ** RADIX_BITS)
_C_TYPES = {
    np.dtype(np.uint8): "uchar",
    np.dtype(np.uint16): "ushort",
    np.dtype(np.int16): "short",
    np.dtype(np.int32): "int",
    np.dtype(np.uint32): "uint",
    np.dtype(np.float32): "float",
}


# uploads of at least this many bytes to a GPU go through page-locked staging buffers of STAGE_BYTES each
PINNED_FROM_BYTES = 32 << 20
STAGE_BYTES = 32 << 20


_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"\s*(/\*.*\*/|//.*)?\s*$')  # a trailing comment allowed
_COMMON = "engine.backend.kernels"  # where an include not found beside the including file is looked for


def kernel_source(package: str, name: str, seen: set[str] | None = None) -> str:
    """The OpenCL C of ``package``'s ``name`` with every ``#include "file.cl"`` line replaced by that file's text
    (itself resolved the same way), found beside the including file or else in ``engine/backend/kernels``; a file
    is inlined once per program (a second include of it is dropped). The driver gets one self-contained source (no
    include path: PoCL's cache and NVIDIA's build see the whole text)."""
    seen = set() if seen is None else seen
    path = importlib.resources.files(package).joinpath(name)
    seen.add(f"{package}:{name}")
    out = []
    for line in path.read_text().splitlines():
        match = _INCLUDE.match(line)
        if match is None:
            out.append(line)
            continue
        where = _include_package(package, match.group(1), f"{package}:{name}")
        key = f"{where}:{match.group(1)}"
        out.append(f"// include {key}{' (already included)' if key in seen else ''}")
        if key not in seen:
            out.append(kernel_source(where, match.group(1), seen))
    return "\n".join(out) + "\n"


def _include_package(package: str, name: str, including: str) -> str:
    for where in (package, _COMMON):
        if importlib.resources.files(where).joinpath(name).is_file():
            return where
    raise ValueError(f'OpenCL source {including}: #include "{name}" is neither in {package} nor in {_COMMON}')


class CLArray:
    """A device array of the OpenCL backend: a ``cl.Buffer`` (``buf``), its ``shape`` and element ``dtype`` (a numpy
    dtype, or VEC3F / VEC3I for arrays of packed triples). A view into another array holds it (``base``), so the
    allocation tracker counts the memory until both are gone."""

    def __init__(
        self, backend: OpenCLBackend, buf: Any, shape: tuple[int, ...], dtype: DType, base: CLArray | None = None
    ) -> None:
        self.backend, self.buf, self.shape, self.dtype, self.base = backend, buf, shape, dtype, base

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    @property
    def nbytes(self) -> int:
        return self.size * itemsize(self.dtype)

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def __repr__(self) -> str:
        return f"CLArray(shape={self.shape}, dtype={self.dtype}, on {self.backend.label})"


def _shape(shape: int | tuple[int, ...]) -> tuple[int, ...]:
    return (int(shape),) if isinstance(shape, int | np.integer) else tuple(int(s) for s in shape)


class _CLPeak(PeakTracker):
    """The backend's allocation tracker: bytes of the buffers it allocated that are still alive, at their most."""

    how = "opencl backend allocation tracker"

    def __init__(self, backend: OpenCLBackend) -> None:
        self.backend = backend
        self.baseline = 0

    def start(self) -> PeakTracker:
        self.backend.synchronize()
        with self.backend.lock:
            self.baseline = self.backend.live
            self.backend.high = self.backend.live
        return self

    def peak(self) -> int | None:
        return self.backend.high - self.baseline


class OpenCLBackend(Backend):
    """OpenCL on one device (``opencl_devices()[index]``)."""

    kind = "opencl"

    def __init__(self, device: Any, index: int) -> None:
        import pyopencl as cl

        self.cl, self.device, self.index = cl, device, index
        self.context = cl.Context([device])
        self.queue = cl.CommandQueue(self.context)
        self.is_host = bool(device.type & cl.device_type.CPU)
        self.spec = f"opencl:{index}"
        self.label = f"opencl:{index} {device.name.strip()} ({device.platform.name.strip()})"
        self.align = max(device.mem_base_addr_align // 8, 1)  # sub-buffer origins, in bytes
        self.options = ["-cl-fp32-correctly-rounded-divide-sqrt"] if self._correct_division() else []
        self.programs: dict[tuple[str, str], Any] = {}
        self.kernels: dict[tuple[str, str], Any] = {}
        self.lock = threading.Lock()
        self.live = self.high = 0

    def _correct_division(self) -> bool:
        fp = self.device.single_fp_config
        return bool(fp & self.cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT)

    # -- memory ---------------------------------------------------------------------------------------------------
    def _alloc(self, shape: tuple[int, ...], dtype: DType, hostbuf: np.ndarray | None = None) -> CLArray:
        nbytes = max(int(np.prod(shape)) * itemsize(dtype), 1)  # OpenCL has no empty buffer
        mf = self.cl.mem_flags
        if hostbuf is not None and hostbuf.nbytes:
            buf = self.cl.Buffer(self.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=hostbuf)
        else:
            buf = self.cl.Buffer(self.context, mf.READ_WRITE, size=nbytes)
        arr = CLArray(self, buf, shape, dtype if is_vector(dtype) else np.dtype(dtype))
        with self.lock:
            self.live += nbytes
            self.high = max(self.high, self.live)
        weakref.finalize(arr, self._release, nbytes)
        return arr

    def _release(self, nbytes: int) -> None:
        with self.lock:
            self.live -= nbytes

    def empty(self, shape: int | tuple[int, ...], dtype: DType) -> CLArray:
        return self._alloc(_shape(shape), dtype)

    def zeros(self, shape: int | tuple[int, ...], dtype: DType) -> CLArray:
        return self.full(shape, 0, dtype)

    def full(self, shape: int | tuple[int, ...], value: float, dtype: DType) -> CLArray:
        arr = self._alloc(_shape(shape), dtype)
        self.fill(arr, value)
        return arr

    def fill(self, arr: CLArray, value: float) -> None:
        if arr.size:
            pattern = np.asarray([value], dtype=host_dtype(arr.dtype))
            self.cl.enqueue_fill_buffer(self.queue, arr.buf, pattern, 0, arr.nbytes)

    def nbytes(self, arr: CLArray) -> int:
        return arr.nbytes

    # -- copies ---------------------------------------------------------------------------------------------------
    def from_host(self, host: np.ndarray, dtype: DType | None = None) -> CLArray:
        host = np.ascontiguousarray(host)
        if is_vector(dtype):
            return self._alloc((host.size // components(dtype),), dtype, host.astype(host_dtype(dtype), copy=False))
        if host.dtype not in _C_TYPES:
            raise ValueError(f"Expected an array of uint8, uint16, int16, int32, uint32 or float32, got {host.dtype}")
        if self.is_host or host.nbytes < PINNED_FROM_BYTES:
            return self._alloc(host.shape, host.dtype, host)
        arr = self._alloc(host.shape, host.dtype)
        self.upload_pinned(arr, host)
        return arr

    def upload_pinned(self, dst: CLArray, host: np.ndarray) -> None:
        """``host`` into ``dst`` through page-locked staging buffers a chunk at a time: a GPU driver copies pageable
        memory slowly (NVIDIA's OpenCL on the H100 host: 2 GB of scan in 1.2 s, against 0.24 s for CUDA from
        Warp's pinned ring). Each chunk is written into a mapped staging buffer and copied on the queue."""
        cl = self.cl
        flat = np.ascontiguousarray(host).reshape(-1).view(np.uint8)
        stages = self._staging()
        for i, start in enumerate(range(0, flat.size, STAGE_BYTES)):
            chunk = flat[start : start + STAGE_BYTES]
            stage = stages[i % len(stages)]
            # in order: the map waits for this buffer's last copy (the other buffer's copy runs meanwhile)
            mapped, _ = cl.enqueue_map_buffer(
                self.queue, stage, cl.map_flags.WRITE_INVALIDATE_REGION, 0, (chunk.size,), np.uint8, is_blocking=True
            )
            mapped[:] = chunk
            mapped.base.release(self.queue)
            cl.enqueue_copy(self.queue, dst.buf, stage, byte_count=chunk.size, dst_offset=start)

    def _staging(self) -> list[Any]:
        if not hasattr(self, "_stages"):
            flags = self.cl.mem_flags.READ_ONLY | self.cl.mem_flags.ALLOC_HOST_PTR
            self._stages = [self.cl.Buffer(self.context, flags, size=STAGE_BYTES) for _ in range(2)]
        return self._stages

    def upload(self, dst: CLArray, host: np.ndarray, dst_offset: int = 0) -> None:
        host = np.ascontiguousarray(host, dtype=host_dtype(dst.dtype))
        if host.nbytes:
            self.cl.enqueue_copy(self.queue, dst.buf, host, dst_offset=dst_offset * itemsize(dst.dtype))

    def to_host(self, arr: CLArray, count: int | None = None) -> np.ndarray:
        n = arr.shape[0] if count is None else count
        shape = (n, components(arr.dtype)) if is_vector(arr.dtype) else (n, *arr.shape[1:])
        out = np.empty(shape, host_dtype(arr.dtype))
        if out.nbytes:
            self.cl.enqueue_copy(self.queue, out, arr.buf, is_blocking=True)
        return out

    def download(self, dst: np.ndarray, src: CLArray, src_offset: int = 0) -> None:
        if dst.size:
            offset = src_offset * itemsize(src.dtype)
            self.cl.enqueue_copy(self.queue, dst.reshape(-1), src.buf, src_offset=offset, is_blocking=True)

    def copy(
        self, dst: CLArray, src: CLArray, dst_offset: int = 0, src_offset: int = 0, count: int | None = None
    ) -> None:
        size = itemsize(src.dtype)
        n = src.size - src_offset if count is None else count
        if n > 0:
            self.cl.enqueue_copy(
                self.queue,
                dst.buf,
                src.buf,
                byte_count=n * size,
                src_offset=src_offset * size,
                dst_offset=dst_offset * size,
            )

    def view(self, arr: CLArray, lo: int, hi: int) -> CLArray:
        shape = (hi - lo, *arr.shape[1:])
        row = int(np.prod(arr.shape[1:])) * itemsize(arr.dtype)
        if lo == 0:
            return CLArray(self, arr.buf, shape, arr.dtype, base=arr)
        if arr.base is None and (lo * row) % self.align == 0 and (hi - lo) * row > 0:
            return CLArray(self, arr.buf.get_sub_region(lo * row, (hi - lo) * row), shape, arr.dtype, base=arr)
        out = self._alloc(shape, arr.dtype)  # an origin the device cannot start a sub-buffer at: copied
        self.copy(out, arr, 0, lo * row // itemsize(arr.dtype), int(np.prod(shape)))
        return out

    def clone(self, arr: CLArray) -> CLArray:
        out = self._alloc(arr.shape, arr.dtype)
        self.copy(out, arr)
        return out

    # -- kernels --------------------------------------------------------------------------------------------------
    def scalar(self, value: float, dtype: DType) -> Any:
        return np.array(value, np.dtype(dtype))  # a 0-d array: ``_arg`` passes a Python or numpy float as float32

    def vector(self, values: Any, dtype: DType) -> Any:
        t = np.dtype(dtype)
        rec = np.zeros((), [("x", t), ("y", t), ("z", t)])  # float64: the kernels' ``origin_t``
        rec["x"], rec["y"], rec["z"] = (float(v) for v in values)
        return rec

    def prepared(self, kernel: Kernel, dim: int, args: list[Any]) -> Callable[[], None]:
        return lambda: self.launch(kernel, dim, args)

    def struct(self, spec: Struct, **values: Any) -> Any:
        dtype = np.dtype([(name, t) for name, t in spec.fields])
        rec = np.zeros((), dtype)
        for name, _ in spec.fields:
            rec[name] = values[name]
        return rec

    def program(self, source: str, dtype: DType | None) -> Any:
        """The built program of ``"package:file.cl"`` for the sample type ``dtype`` (``VOL_T``), built once."""
        vol_t = _C_TYPES[np.dtype(dtype)] if dtype is not None else "float"
        key = (source, vol_t)
        if key not in self.programs:
            package, _, name = source.partition(":")
            prg = self.cl.Program(self.context, kernel_source(package, name))
            with warnings.catch_warnings():  # a driver's build log (informational) is not the engine's warning
                warnings.simplefilter("ignore", self.cl.CompilerWarning)
                self.programs[key] = prg.build(options=[*self.options, f"-DVOL_T={vol_t}"])
        return self.programs[key]

    def _kernel(self, kernel: Kernel, dtype: DType | None) -> Any:
        source, _, function = kernel.opencl.rpartition(":")
        prg = self.program(source, dtype)
        key = (source + (str(np.dtype(dtype)) if dtype is not None else ""), function)
        if key not in self.kernels:
            self.kernels[key] = self.cl.Kernel(prg, function)
        return self.kernels[key]

    def _arg(self, a: Any) -> Any:
        if isinstance(a, CLArray):
            return a.buf
        if type(a) in (bool, int):  # Python scalars are 32-bit (as Warp's ``int`` and ``float``)
            return np.int32(a)
        if type(a) is float:  # not np.float64, a subclass of float: numpy scalars keep their width
            return np.float32(a)
        return a  # numpy scalars and struct records as they are

    def launch(self, kernel: Kernel, dim: int | tuple[int, ...], args: list[Any], dtype: DType | None = None) -> None:
        gsize = _shape(dim)[::-1]
        if min(gsize) <= 0:
            return
        k = self._kernel(kernel, dtype)
        with self.lock:
            k.set_args(*(self._arg(a) for a in args))
            self.cl.enqueue_nd_range_kernel(self.queue, k, gsize, None)

    def exclusive_scan(self, src: CLArray, dst: CLArray) -> int:
        sums = self._scan(src, dst)
        if sums is None:
            return 0
        total = np.empty(1, np.int32)
        self.cl.enqueue_copy(self.queue, total, sums.buf, src_offset=(sums.size - 1) * 4, is_blocking=True)
        return int(total[0])

    def prefix_sum(self, src: CLArray, dst: CLArray) -> None:
        self._scan(src, dst)

    def _scan(self, src: CLArray, dst: CLArray) -> CLArray | None:
        """In ``scan.cl``'s three launches: up to ``SCAN_CHUNKS`` runs summed, the sums scanned, the runs scanned;
        returns the run sums (their last element is the total), None for an empty ``src``."""
        n = src.size
        if n == 0:
            return None
        chunks = min(SCAN_CHUNKS, n)
        run = -(-n // chunks)
        chunks = -(-n // run)
        sums = self.empty(chunks + 1, np.int32)
        self.launch(_SCAN_SUMS, chunks, [src, np.int64(n), np.int64(run), sums])
        self.launch(_SCAN_TOP, 1, [sums, chunks])
        self.launch(_SCAN_RUNS, chunks, [src, np.int64(n), np.int64(run), sums, dst])
        return sums

    def sort_pairs(self, keys: CLArray, values: CLArray, n: int) -> None:
        """On the device (``radix.cl``: a stable LSD radix sort, 4 bits a pass over the bits the keys' range spans,
        between the arrays' two halves); one sync point, for the keys' range."""
        if n <= 1:
            return
        run = -(-n // min(SCAN_CHUNKS, n))
        chunks = -(-n // run)
        ends = self.empty(2 * chunks, np.int64)  # each run's smallest key, then each run's largest
        self.launch(_RADIX_RANGE, chunks, [keys, np.int64(n), np.int64(run), ends])
        lows, highs = self.to_host(ends).reshape(2, chunks)  # sync point: one read
        base = int(lows.min())
        span = int(highs.max()) - base
        passes = -(-span.bit_length() // RADIX_BITS)
        counts = self.empty(chunks << RADIX_BITS, np.int32)
        offsets = self.empty(chunks << RADIX_BITS, np.int32)
        src, dst = 0, n
        for p in range(passes):
            shift = np.int32(p * RADIX_BITS)
            common = [np.int64(n), np.int64(run), np.int64(base), shift, np.int32(chunks)]
            self.launch(_RADIX_DIGITS, chunks, [keys, np.int64(src), *common, counts])
            self.prefix_sum(counts, offsets)
            self.launch(_RADIX_SCATTER, chunks, [keys, values, np.int64(src), np.int64(dst), *common, offsets])
            src, dst = dst, src
        if src:  # an odd number of passes ended in the second halves
            self.copy(keys, keys, 0, n, n)
            self.copy(values, values, 0, n, n)

    def compact(self, flags: CLArray) -> tuple[CLArray, CLArray, int]:
        n_in = flags.size
        pos = self.empty(n_in, np.int32)
        n = self.exclusive_scan(flags, pos)
        indices = self.empty(max(n, 1), np.int32)
        ranks = self.empty(n_in, np.int32)
        self.launch(COMPACT, n_in, [flags, pos, indices, ranks])
        return indices, ranks, n

    def synchronize(self) -> None:
        self.queue.finish()

    def peak_tracker(self) -> PeakTracker:
        return _CLPeak(self)

    def default_budget(self) -> int:
        if self.is_host:
            return host_budget()
        return int(self.device.global_mem_size * 0.5)
