"""Host copies of device arrays through the process's pinned buffer (``engine.staging``)."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from engine.staging import ALIGN, HostCopies, host_copies


def _arrays(device: str) -> list[wp.array]:
    rng = np.random.default_rng(7)
    return [
        wp.array(rng.random((1000, 12), dtype=np.float32), dtype=wp.float32, device=device),
        wp.array(rng.random((333, 3), dtype=np.float32), dtype=wp.vec3, device=device),
        wp.array(rng.integers(0, 1 << 30, (501, 3), dtype=np.int32), dtype=wp.vec3i, device=device),
    ]


def test_copies_into_one_buffer_keep_every_value():
    """Arrays packed one after another (aligned) into one host buffer come back whole: none overwrites another."""
    arrays = _arrays("cpu")
    nbytes = sum(a.capacity for a in arrays) + len(arrays) * ALIGN
    buf = wp.empty(nbytes, dtype=wp.uint8, device="cpu")
    to_host = HostCopies(buf, wp.get_device("cpu"))
    got = [to_host(a) for a in arrays]
    to_host.wait()
    for a, g in zip(arrays, got, strict=True):
        np.testing.assert_array_equal(g, a.numpy())
        assert buf.ptr <= g.ctypes.data < buf.ptr + nbytes  # a view of the buffer, not a new array
    with pytest.raises(ValueError, match="planned"):
        to_host(arrays[0])


def test_without_cuda_the_copies_are_plain_arrays():
    with host_copies("cpu", 1 << 20) as to_host:
        assert not to_host.pinned
        a = _arrays("cpu")[1]
        np.testing.assert_array_equal(to_host(a), a.numpy())


@pytest.mark.gpu
def test_cuda_copies_go_through_one_reused_pinned_buffer():
    arrays = _arrays("cuda:0")
    nbytes = sum(a.capacity for a in arrays) + len(arrays) * ALIGN
    ptrs = []
    for _ in range(2):
        with host_copies("cuda:0", nbytes) as to_host:
            assert to_host.pinned and to_host.buf.pinned
            got = [to_host(a) for a in arrays]
            to_host.wait()
            for a, g in zip(arrays, got, strict=True):
                np.testing.assert_array_equal(g, a.numpy())
            ptrs.append(to_host.buf.ptr)
            with host_copies("cuda:0", nbytes) as other:  # held: a second job at the same time copies plainly
                assert not other.pinned
    assert ptrs[0] == ptrs[1], "the pinned buffer is allocated once and reused"
