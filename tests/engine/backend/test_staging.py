"""Host copies of device arrays through the process's pinned buffer (``engine.staging``), and the plane feed that
uploads a streamed volume through a pinned ring (``engine.isosurface.feed``)."""

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


def test_pinned_buffers_hold_what_is_asked_in_8_byte_elements():
    """(an array of bytes would stop at 2 GiB: Warp's dimensions are 32-bit; a 4 GiB buffer is allowed)"""
    from engine.staging import pinned_bytes

    for n in (1, 8, 1001):
        buf = pinned_bytes(n, pinned=False)
        assert buf.capacity >= n and buf.capacity - n < 8 and buf.dtype == wp.int64


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


# ------------------------------------------------------------------------- loaded volumes (engine.io's allocate)
def test_the_volume_buffer_is_reused_only_once_nothing_holds_it(monkeypatch):
    from engine.staging import VolumeBuffer

    monkeypatch.setenv("BONEMESH_PINNED_MAX", "1M")
    volumes = VolumeBuffer(pinned=False)
    first = volumes((4, 8, 8), np.uint16)
    first[...] = 7
    held = volumes((4, 8, 8), np.uint16)  # the first still lives: a plain array of its own
    assert not np.shares_memory(first, held) and volumes.buf.ptr != held.ctypes.data
    plane = first[2]  # a view holds it too
    del first, held
    assert volumes((4, 8, 8), np.uint16).ctypes.data != volumes.buf.ptr
    del plane
    again = volumes((2, 8, 8), np.float32)  # free now: the same memory, any shape and type that fits
    assert again.ctypes.data == volumes.buf.ptr and again.shape == (2, 8, 8) and again.dtype == np.float32
    assert again.flags.c_contiguous and again.flags.writeable
    del again
    big = volumes((64, 64, 64), np.uint16)  # larger: the buffer grows (the old one freed first)
    assert big.ctypes.data == volumes.buf.ptr and volumes.buf.capacity >= big.nbytes
    del big
    past_cap = volumes((1, 1024, 1024), np.uint16)  # 2 MB past the 1 MB cap: plain
    assert past_cap.ctypes.data != volumes.buf.ptr


def test_a_reserved_volume_buffer_serves_the_first_load_without_growing(monkeypatch):
    """A worker's warm-up reserves the buffer for a volume size; a volume up to it then lands in that memory (no
    new allocation), a larger one grows it as before; nothing is reserved past the cap or while a volume holds it."""
    from engine.staging import VolumeBuffer

    monkeypatch.setenv("BONEMESH_PINNED_MAX", "1M")
    volumes = VolumeBuffer(pinned=False)
    assert volumes.reserve(0) == 0 and volumes.buf is None
    assert volumes.reserve(2 << 20) == 0 and volumes.buf is None  # past the 1 MB cap
    held = volumes.reserve(100_000)
    assert held >= 100_000 and volumes.buf.capacity == held
    ptr = volumes.buf.ptr
    first = volumes((10, 50, 100), np.uint16)  # exactly the 100,000 bytes reserved
    assert first.ctypes.data == ptr and volumes.buf.capacity == held
    assert volumes.reserve(200_000) == held and volumes.buf.ptr == ptr  # held by `first`: left as it is
    del first
    assert volumes.reserve(50_000) == held and volumes.buf.ptr == ptr  # already large enough
    assert volumes.reserve(200_000) >= 200_000


def test_warm_up_reserves_load_buffers_only_on_cuda():
    from engine.staging import reserve_load_buffers
    from engine.job.warmup import warm_up

    assert reserve_load_buffers("cpu", 1 << 20, rows=True) == 0  # plain arrays off CUDA: nothing to page-lock
    info = warm_up("cpu", volume_bytes=1 << 20)
    assert info["device"] == "cpu" and info["pinned_bytes"] == 0 and info["seconds"] > 0


def test_a_stack_loads_the_same_into_the_buffer(tmp_path):
    import imagecodecs

    from engine.io import load_volume
    from engine.staging import VolumeBuffer, pinned_volumes

    rng = np.random.default_rng(3)
    stack = rng.integers(0, 4096, (5, 12, 9), dtype=np.uint16)
    folder = tmp_path / "stack"
    folder.mkdir()
    for z, img in enumerate(stack):
        (folder / f"s{z:02d}.png").write_bytes(imagecodecs.png_encode(img))
    volumes = VolumeBuffer(pinned=False)
    got = load_volume(folder, spacing_zyx_mm=(1, 1, 1), allocate=volumes)
    assert got.data.ctypes.data == volumes.buf.ptr
    np.testing.assert_array_equal(got.data, stack)
    np.testing.assert_array_equal(got.data, load_volume(folder, spacing_zyx_mm=(1, 1, 1)).data)
    with pytest.raises(ValueError, match="cannot be filled in place"):
        load_volume(folder, spacing_zyx_mm=(1, 1, 1), allocate=lambda shape, dtype: np.empty(shape, np.float32))
    assert pinned_volumes("cpu") is None  # plain arrays where the device is not CUDA


@pytest.mark.gpu
def test_cuda_workers_load_into_one_reused_pinned_buffer(tmp_path):
    from engine.staging import pinned_volumes

    volumes = pinned_volumes("cuda:0")
    assert volumes is not None and volumes is pinned_volumes("cuda:0")
    a = volumes((3, 64, 64), np.uint16)
    a[...] = np.arange(64, dtype=np.uint16)
    assert volumes.buf.pinned and volumes.buf.ptr == a.ctypes.data
    on_gpu = wp.array(a, device="cuda:0")
    np.testing.assert_array_equal(on_gpu.numpy(), a)
    ptr = volumes.buf.ptr
    del a
    assert volumes((3, 64, 64), np.uint16).ctypes.data == ptr


@pytest.mark.gpu
def test_a_cuda_warm_up_page_locks_the_load_buffers_for_the_size_asked():
    from engine.staging import pinned_rows, pinned_volumes
    from engine.job.warmup import warm_up

    nbytes = 3 * 256 * 256 * 2
    info = warm_up("cuda:0", volume_bytes=nbytes)
    volumes, rows = pinned_volumes("cuda:0"), pinned_rows("cuda:0")
    assert volumes is not None and rows is not None
    assert volumes.buf.pinned and volumes.buf.capacity >= nbytes and rows.buf.capacity >= nbytes + 3 * 256
    assert info["pinned_bytes"] == volumes.buf.capacity + rows.buf.capacity
    ptr = volumes.buf.ptr
    assert volumes((3, 256, 256), np.uint16).ctypes.data == ptr  # the first load fills it as it is


# --------------------------------------------------------------------------------- plane feed (host to device)
def _requests(nz: int, rng: np.random.Generator) -> list[tuple[int, int]]:
    """A slab pass's requests: forward in z, each next slab starting just before the last one ended, some slabs
    redone smaller from the same start, some longer than the ring."""
    out, z = [], 0
    while z < nz - 1:
        hi = min(z + int(rng.integers(1, 40)), nz - 1)
        if rng.random() < 0.3:
            out.append((z, hi))  # too big: redone smaller
            hi = z + max((hi - z) // 2, 1)
        out.append((z, hi))
        z = max(hi - int(rng.integers(0, 3)), z + 1)
    return out


@pytest.mark.parametrize("ring_planes", [2, 7, 64])
def test_plane_feed_uploads_the_planes_asked_for(monkeypatch, device, ring_planes):
    """Whatever the ring's size against the slabs (2 planes, shorter and longer than them), every request gets
    exactly the volume's planes, including one behind the released planes (copied directly)."""
    from engine.isosurface import feed as feeds

    rng = np.random.default_rng(ring_planes)
    vol = rng.integers(0, 4000, (150, 9, 11), dtype=np.uint16)
    monkeypatch.setattr(feeds, "FEED_CHUNK_BYTES", 3 * vol[0].nbytes)
    with feeds.plane_feed(vol, device, ring_bytes=ring_planes * vol[0].nbytes) as feed:
        assert isinstance(feed, feeds.PlaneFeed)
        for zlo, zhi in [*_requests(len(vol), rng), (0, 5)]:
            got = feed.upload(zlo, zhi)
            assert got.device == wp.get_device(device) and got.shape == (zhi - zlo + 1, 9, 11)
            np.testing.assert_array_equal(got.numpy(), vol[zlo : zhi + 1])
    assert not feed.thread.is_alive()


def test_plane_feed_is_held_by_one_job_at_a_time():
    from engine.isosurface import feed as feeds

    vol = np.arange(4 * 5 * 6, dtype=np.float32).reshape(4, 5, 6)
    with feeds.plane_feed(vol, "cpu", force=True) as first, feeds.plane_feed(vol, "cpu", force=True) as second:
        assert isinstance(first, feeds.PlaneFeed) and isinstance(second, feeds.DirectFeed)  # the second: direct
        np.testing.assert_array_equal(second.upload(1, 2).numpy(), vol[1:3])
    with feeds.plane_feed(vol, "cpu") as plain:  # not CUDA: no ring
        assert isinstance(plain, feeds.DirectFeed)
        np.testing.assert_array_equal(plain.upload(0, 3).numpy(), vol)


def test_plane_feed_reports_a_failed_read(monkeypatch):
    """A volume whose planes cannot be read (e.g. a memmap whose disk went away) fails the request with the reason
    and the thread ends."""
    from engine.isosurface import feed as feeds

    class Broken(np.ndarray):
        def __getitem__(self, key):
            if isinstance(key, slice):  # the planes the thread reads
                raise OSError("disk gone")
            return super().__getitem__(key)

    vol = np.zeros((8, 4, 4), np.uint16).view(Broken)
    monkeypatch.setattr(feeds.np, "ascontiguousarray", lambda a: a)
    with pytest.raises(RuntimeError, match="disk gone"), feeds.plane_feed(vol, "cpu", force=True) as feed:
        feed.upload(0, 3)
