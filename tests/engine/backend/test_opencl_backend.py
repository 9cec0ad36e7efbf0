"""The backend interface (``engine.backend.Backend``) on each backend: memory, copies with offsets, views, the
exclusive scan and stream compaction against numpy, the memory high-water mark; and device selection
(``"opencl"`` / ``"opencl:N"``, with clear errors where PyOpenCL or every OpenCL platform is missing)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from engine.backend import VEC3F, VEC3I, get_backend
from engine.device import resolve_backend, resolve_device

REPO = Path(__file__).resolve().parents[3]


@pytest.mark.parametrize("n", [1, 7, 4096, 4097, 100_003])
def test_exclusive_scan_and_compaction_match_numpy(backend, n):
    rng = np.random.default_rng(n)
    values = rng.integers(0, 4, n).astype(np.int32)
    src = backend.from_host(values)
    dst = backend.empty(n, np.int32)
    total = backend.exclusive_scan(src, dst)
    expected = np.concatenate([[0], np.cumsum(values)[:-1]])
    assert total == int(values.sum())
    np.testing.assert_array_equal(backend.to_host(dst), expected)

    flags = (values == 0).astype(np.int32)
    indices, ranks, count = backend.compact(backend.from_host(flags))
    where = np.flatnonzero(flags)
    assert count == len(where)
    np.testing.assert_array_equal(backend.to_host(indices, count), where)
    want_ranks = np.full(n, -1, np.int32)
    want_ranks[where] = np.arange(len(where))
    np.testing.assert_array_equal(backend.to_host(ranks), want_ranks)


def test_compacting_nothing(backend):
    indices, _, count = backend.compact(backend.zeros(9, np.int32))
    assert count == 0 and len(indices) >= 1  # at least one element allocated


def test_copies_with_offsets_views_and_fills(backend):
    host = np.arange(40, dtype=np.int32)
    a = backend.from_host(host)
    b = backend.full(50, -1, np.int32)
    backend.copy(b, a, dst_offset=5, src_offset=10, count=20)
    want = np.full(50, -1, np.int32)
    want[5:25] = host[10:30]
    np.testing.assert_array_equal(backend.to_host(b), want)
    backend.upload(b, np.array([7, 8, 9], np.int32), dst_offset=47)
    assert backend.to_host(b)[-3:].tolist() == [7, 8, 9]
    assert backend.to_host(b, 3).tolist() == [-1] * 3
    backend.fill(b, 4)
    assert set(backend.to_host(b).tolist()) == {4}
    assert backend.to_host(backend.zeros((2, 3), np.float32)).tolist() == [[0.0] * 3] * 2

    # odd planes (an unaligned view is a copy on OpenCL) and 2 KiB planes (a sub-buffer)
    for vol in (np.arange(5 * 3 * 7, dtype=np.uint16).reshape(5, 3, 7), np.arange(5 * 512, dtype=np.float32)):
        vol = vol.reshape(5, -1, 7 if vol.dtype == np.uint16 else 16)
        dev = backend.from_host(vol)
        for lo, hi in ((0, 2), (1, 4), (3, 5)):
            view = backend.view(dev, lo, hi)
            assert tuple(view.shape) == (hi - lo, *vol.shape[1:])
            np.testing.assert_array_equal(backend.to_host(view), vol[lo:hi])
            assert backend.nbytes(view) == vol[lo:hi].nbytes


def test_vector_arrays_round_trip(backend):
    pts = np.arange(12, dtype=np.float32).reshape(4, 3) / 3
    ids = np.arange(9, dtype=np.int32).reshape(3, 3)
    v, f = backend.from_host(pts, VEC3F), backend.from_host(ids, VEC3I)
    assert len(v) == 4 and len(f) == 3
    np.testing.assert_array_equal(backend.to_host(v).reshape(-1, 3), pts)
    np.testing.assert_array_equal(backend.to_host(f, 2).reshape(-1, 3), ids[:2])
    both = backend.empty(7, VEC3F)
    backend.copy(both, v, dst_offset=3, count=4)
    np.testing.assert_array_equal(backend.to_host(both).reshape(-1, 3)[3:], pts)


def test_quadric_arrays_clones_sorts_and_scans_without_a_total(backend):
    """The interface's words for the decimation's device mesh (no ``kind`` branch outside the backends)."""
    from engine.backend.base import VEC10D
    from engine.decimation.kernel_specs import ALIVE_FLAGS

    q = np.arange(40, dtype=np.float64).reshape(4, 10) / 7
    dq = backend.from_host(q, VEC10D)
    assert len(dq) == 4 and backend.nbytes(dq) == 320
    both = backend.empty(6, VEC10D)
    backend.copy(both, dq, dst_offset=2)  # counted in quadrics
    np.testing.assert_array_equal(backend.to_host(both)[2:], q)
    np.testing.assert_array_equal(backend.to_host(backend.clone(dq)), q)
    keys = np.array([5, 1, 5, 0, 1, 9, 5], np.int64)
    dk, dv = backend.empty(14, np.int64), backend.from_host(np.arange(14, dtype=np.int32))
    backend.upload(dk, np.concatenate([keys, keys]))
    backend.sort_pairs(dk, dv, len(keys))
    np.testing.assert_array_equal(backend.to_host(dv, 7), np.argsort(keys, kind="stable"))
    counts = np.array([3, 0, 2, 5], np.int32)
    out = backend.empty(4, np.int32)
    backend.prefix_sum(backend.from_host(counts), out)
    np.testing.assert_array_equal(backend.to_host(out), [0, 3, 3, 5])
    faces = backend.from_host(np.array([[0, 1, 2], [-1, -1, -1]], np.int32), VEC3I)
    flags = backend.full(2, 7, np.int32)
    run = backend.prepared(ALIVE_FLAGS, 2, [faces, flags])
    run()
    np.testing.assert_array_equal(backend.to_host(flags), [1, 0])
    assert backend.scalar(0.1, np.float64) == np.float64(0.1)  # not narrowed to float32
    from engine.decimation.meshops import xyz

    assert xyz(backend.vector((1, 2, 3), np.float64)) == (1, 2, 3)


@pytest.mark.parametrize(
    ("n", "kind"),
    [(2, "few"), (4097, "few"), (100_003, "cells"), (20_000, "wide"), (5_000, "equal"), (9_999, "negative")],
)
def test_sort_pairs_is_numpys_stable_argsort(backend, n, kind):
    """The device sort (a radix sort on OpenCL) orders by key and keeps equal keys in their order, for keys as the
    clustering packs them (21 bits a cell axis), few distinct ones, the full int64 range, one value, negatives."""
    rng = np.random.default_rng(n)
    keys = {
        "few": rng.integers(0, 5, n),
        "cells": (rng.integers(0, 1 << 21, (n, 3)) << np.array([42, 21, 0])).sum(axis=1),
        "wide": rng.integers(np.iinfo(np.int64).min, np.iinfo(np.int64).max, n, dtype=np.int64),
        "equal": np.full(n, 123456789),
        "negative": rng.integers(-(1 << 40), 1 << 20, n),
    }[kind].astype(np.int64)
    dk = backend.empty(2 * n, np.int64)
    backend.upload(dk, np.concatenate([keys, np.zeros(n, np.int64)]))
    dv = backend.from_host(np.arange(2 * n, dtype=np.int32))
    backend.sort_pairs(dk, dv, n)
    order = np.argsort(keys, kind="stable")
    np.testing.assert_array_equal(backend.to_host(dv, n), order)
    np.testing.assert_array_equal(backend.to_host(dk, n), keys[order])


def test_the_memory_high_water_mark_sees_an_allocation(backend):
    tracker = backend.peak_tracker().start()
    held = backend.zeros(1 << 18, np.float32)  # 1 MiB
    peak = tracker.peak()
    tracker.stop()
    assert peak is not None and peak >= 1 << 20, (peak, tracker.how)
    assert backend.nbytes(held) == 1 << 20
    assert backend.default_budget() > 0


def test_selection_names_the_backend_and_its_device(opencl):
    assert resolve_backend("opencl") is opencl is get_backend("opencl:0")
    assert opencl.kind == "opencl" and opencl.label.startswith("opencl:0 ")
    assert resolve_backend("cpu").kind == "warp"
    assert str(resolve_device("opencl")) == "cpu"  # the Warp device of the stages not on OpenCL yet
    with pytest.raises(ValueError, match=r"available OpenCL device \(\d+ present: opencl:0 "):
        resolve_backend("opencl:64")
    with pytest.raises(ValueError, match="Expected device"):
        resolve_device("opencl:gpu")


def _run(code: str, **env: str) -> subprocess.CompletedProcess[str]:
    import os

    return subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, env={**os.environ, **env}
    )


def test_without_an_opencl_platform_the_error_says_what_to_install(tmp_path):
    code = "from engine.device import resolve_backend\nresolve_backend('opencl')"
    out = _run(code, OCL_ICD_VENDORS=str(tmp_path), OCL_ICD_FILENAMES="")  # the ICD loader finds no driver
    assert out.returncode != 0
    assert "ValueError: device 'opencl': no OpenCL platform is installed" in out.stderr, out.stderr
    assert "pocl-opencl-icd" in out.stderr


def test_without_pyopencl_the_error_names_the_extra():
    code = "import sys\nsys.modules['pyopencl'] = None\nfrom engine.device import resolve_device\n"
    code += "resolve_device('opencl:1')"
    out = _run(code)
    assert out.returncode != 0
    assert "ValueError: device 'opencl' needs PyOpenCL" in out.stderr and "bonemesh[opencl]" in out.stderr


def test_importing_the_backends_loads_neither_warp_nor_pyopencl():
    code = "import sys, engine.backend, engine.device\nprint('warp' in sys.modules, 'pyopencl' in sys.modules)"
    out = _run(code)
    assert out.stdout.strip() == "False False", out.stderr


def test_large_uploads_to_a_gpu_go_through_pinned_staging_with_the_same_values(opencl):
    """``upload_pinned`` (what ``from_host`` uses for large arrays on a GPU): chunks through two page-locked
    staging buffers, the last one partial, the same bytes (run here on PoCL by calling it directly)."""
    from engine.backend import opencl_backend

    data = np.random.default_rng(3).integers(0, 60000, size=opencl_backend.STAGE_BYTES + 12346, dtype=np.uint16)
    dst = opencl.empty(data.shape, np.uint16)
    opencl.upload_pinned(dst, data)
    assert np.array_equal(opencl.to_host(dst), data)


def test_kernel_sources_inline_their_includes_once():
    """``#include "x.cl"`` (engine.backend.opencl_backend.kernel_source): found beside the file or in the backend's
    kernels, each file once per program, so a driver gets one self-contained source."""
    from engine.backend.opencl_backend import kernel_source

    text = kernel_source("engine.decimation.kernels", "price.cl")
    assert not any(line.lstrip().startswith("#include") for line in text.splitlines())
    included = [line for line in text.splitlines() if line.startswith("// include")]
    assert included == [  # pass.cl includes the backend's common.cl; each file once
        "// include engine.decimation.kernels:pass.cl",
        "// include engine.backend.kernels:common.cl",
        "// include engine.decimation.kernels:linalg.cl",
    ]
    assert text.count("#define FREE") <= 1
    with pytest.raises(ValueError, match=re.escape('#include "nowhere.cl"')):
        from engine.backend import opencl_backend

        opencl_backend._include_package("engine.decimation.kernels", "nowhere.cl", "test")
