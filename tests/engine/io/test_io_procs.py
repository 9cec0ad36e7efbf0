"""DICOM decoded in processes (``engine.io.procs``) against threads and the serial loop: same volumes, same
errors, workers that do not outlive the load, and the fallback to threads where processes cannot be started."""

from __future__ import annotations

import io
import json
import multiprocessing
import os
import subprocess
import sys
import tarfile
import textwrap
import time
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydicom.uid import JPEG2000Lossless, RLELossless

import engine.io.dicom as dicom_mod
import engine.io.procs as procs
from engine.errors import InputError
from engine.io import load_volume
from engine.io.archive import open_members
from engine.io.parallel import ordered_map
from engine.io.readers import read_where
from engine.types import Volume
from tests.engine.decode_spy import load_counting_pools
from tests.engine.dicom_factory import break_rle, series

REPO = Path(__file__).resolve().parents[3]
POSITIONS = [float(z) for z in range(11)]


def _field(p: np.ndarray) -> np.ndarray:
    return 40.0 * np.sin(p[..., 0] / 3.0) + 5.0 * p[..., 1] - 7.0 * p[..., 2]


def _zip(path: Path, files: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name in reversed(list(files)):  # stored out of slice order
            zf.writestr(name, files[name])
    return path


def _tar(path: Path, files: dict[str, bytes], mode: str = "w") -> Path:
    with tarfile.open(path, mode) as tf:
        for name, data in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return path


def _assert_same(a: Volume, b: Volume) -> None:
    assert a.data.dtype == b.data.dtype and a.data.shape == b.data.shape
    np.testing.assert_array_equal(a.data, b.data)
    assert (a.spacing_zyx_mm, a.origin_mm, a.direction) == (b.spacing_zyx_mm, b.origin_mm, b.direction)
    assert (a.units, a.patient_frame, a.source) == (b.units, b.patient_frame, b.source)


class _Pools:
    """The decode pools that ran (closed after use, not given up at start) and their workers' pids."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.made: list[procs.DecodePool] = []
        self.pids: set[int] = set()
        real_close = procs.DecodePool.close

        def close(pool: procs.DecodePool) -> None:
            self.made.append(pool)
            self.pids.update(pool.pool._processes or {})  # type: ignore[attr-defined]
            real_close(pool)

        monkeypatch.setattr(procs.DecodePool, "close", close)


def _gone(pids: set[int], timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        alive = set()
        for pid in pids:
            try:
                with open(f"/proc/{pid}/stat") as fh:
                    if fh.read().split(") ")[-1][0] != "Z":
                        alive.add(pid)
            except (FileNotFoundError, ProcessLookupError):
                pass
        if not alive:
            return True
        time.sleep(0.05)
    return False


@pytest.mark.parametrize(
    ("syntax", "extra"),
    [
        (None, {}),
        (RLELossless, {}),
        (JPEG2000Lossless, {}),
        (None, {"slope": 2.0, "intercept": -2048.0}),  # integral rescale: int16 in place, in the shared volume
        (None, {"slope": 0.5, "intercept": -1024.0}),  # fractional rescale: float32
    ],
    ids=["explicit-le", "rle", "j2k-lossless", "int-rescale", "float-rescale"],
)
def test_processes_equal_threads_and_serial(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, syntax: str | None, extra: dict[str, float]
) -> None:
    kwargs: dict[str, object] = dict(extra)
    if syntax is not None:
        kwargs["transfer_syntax"] = syntax
    path = _zip(tmp_path / "d.zip", series(_field, positions_mm=POSITIONS, shape=(40, 36), **kwargs))
    serial = load_volume(path, threads=1)
    threaded = load_volume(path, threads=3, processes=False)
    pools = _Pools(monkeypatch)
    in_procs = load_volume(path, threads=3, processes=True)
    assert len(pools.made) == 1 and len(pools.pids) == 3  # really decoded in 3 processes
    _assert_same(serial, threaded)
    _assert_same(serial, in_procs)
    assert in_procs.units == "HU" and in_procs.source["files"] == len(POSITIONS)
    assert _gone(pools.pids), "a decode process outlived the load"


@pytest.mark.parametrize("kind", ["tar", "folder", "tar.gz"])
def test_other_containers(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, kind: str) -> None:
    files = series(_field, positions_mm=POSITIONS, drift=(0.0, 0.3, 0.0))  # tilted: resampled after decoding
    if kind == "folder":
        path = tmp_path / "series"
        path.mkdir()
        for name, data in files.items():
            (path / name).write_bytes(data)
    else:
        path = _tar(tmp_path / f"s.{kind}", files, "w:gz" if kind == "tar.gz" else "w")
    serial = load_volume(path, threads=1)
    assert serial.source["resampled"] is True
    pools = _Pools(monkeypatch)
    _assert_same(serial, load_volume(path, threads=2, processes=True))
    # a compressed tar's members are spooled in this process: they are decoded on threads
    assert len(pools.made) == (0 if kind == "tar.gz" else 1)


def test_first_failing_slice_is_named_as_in_the_serial_loop(tmp_path: Path) -> None:
    files = series(_field, positions_mm=[float(z) for z in range(30)], transfer_syntax=RLELossless)
    break_rle(files, ("IM13", "IM21"))
    path = _zip(tmp_path / "r.zip", files)
    messages = []
    for threads, processes in ((1, False), (3, True)):
        with pytest.raises(InputError, match=r"cannot decode the pixels of IM13") as err:
            load_volume(path, threads=threads, processes=processes)
        messages.append(str(err.value))
    assert messages[0] == messages[1]


def test_default_uses_processes_for_long_series_on_enough_cpus(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(dicom_mod, "PROCESS_MIN_FILES", 8)
    monkeypatch.setattr(dicom_mod, "PROCESS_MIN_WORKERS", 3)
    short = _zip(tmp_path / "short.zip", series(_field, positions_mm=POSITIONS[:7]))
    long = _zip(tmp_path / "long.zip", series(_field, positions_mm=POSITIONS[:8]))
    pools = _Pools(monkeypatch)
    load_volume(short, threads=3)
    load_volume(long, threads=2)  # too few CPUs for the default
    assert pools.made == []
    load_volume(long, threads=3)
    assert len(pools.made) == 1
    load_volume(long, threads=1, processes=True)  # one thread is the serial loop, whatever is asked
    load_volume(long, threads=3, processes=False)
    assert len(pools.made) == 1


def _load_in_child(path: str, drop_daemon_flag: bool) -> dict[str, object]:
    """Runs in a daemonic pool child, as Celery's prefork children are (billiard: see the worker test)."""
    if drop_daemon_flag:
        multiprocessing.current_process()._config["daemon"] = False  # type: ignore[attr-defined]
    used, vol = load_counting_pools(path)
    return {"unavailable": procs.unavailable(), "pools": used, "data": vol.data.tolist()}


@pytest.mark.parametrize("drop_daemon_flag", [False, True], ids=["daemonic", "flag-dropped"])
def test_daemonic_process_falls_back_to_threads(tmp_path: Path, drop_daemon_flag: bool) -> None:
    path = _zip(tmp_path / "d.zip", series(_field, positions_mm=POSITIONS))
    serial = load_volume(path, threads=1)
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(1) as pool:  # a multiprocessing.Pool's workers are daemonic
        got = pool.apply(_load_in_child, (str(path), drop_daemon_flag))
    np.testing.assert_array_equal(np.array(got["data"], dtype=serial.data.dtype), serial.data)
    if drop_daemon_flag:
        assert got["unavailable"] is None and got["pools"] == [2]
    else:
        assert got["unavailable"] == "a daemonic process may not start processes" and got["pools"] == []


def test_workers_die_with_a_killed_parent(tmp_path: Path) -> None:
    """A job killed at its hard time limit (SIGKILL) leaves no decode process behind."""
    script = textwrap.dedent(
        """
        import json, os, time
        from engine.io.procs import start_pool

        if __name__ == "__main__":
            with start_pool(2) as dp:
                list(dp.pool.map(os.getpid, [], chunksize=1))
                futures = [dp.pool.submit(time.sleep, 0.3) for _ in range(4)]
                for f in futures:
                    f.result()
                print(json.dumps(sorted(dp.pool._processes)), flush=True)
                time.sleep(600)
        """
    )
    (tmp_path / "hold.py").write_text(script)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    with subprocess.Popen(
        [sys.executable, str(tmp_path / "hold.py")], stdout=subprocess.PIPE, text=True, env=env, cwd=tmp_path
    ) as child:
        try:
            assert child.stdout is not None
            pids = set(json.loads(child.stdout.readline()))
            assert len(pids) == 2 and _gone(pids, timeout=0.5) is False
        finally:
            child.kill()
    assert _gone(pids, timeout=20), f"decode processes {pids} outlived their killed parent"


def _square_or_fail(k: int) -> int:
    if k in (13, 17):
        raise ValueError(f"item {k}")
    return k * k


def test_ordered_map_in_chunks_on_processes_keeps_order_and_the_first_failure() -> None:
    with procs.start_pool(2) as dp:
        assert dp is not None
        for chunk in (1, 3, 8):
            assert list(ordered_map(_square_or_fail, range(13), 2, dp.pool, chunk)) == [k * k for k in range(13)]
            got = []
            with pytest.raises(ValueError, match="item 13"):
                for v in ordered_map(_square_or_fail, range(30), 2, dp.pool, chunk):
                    got.append(v)
            assert got == [k * k for k in range(13)]
    # the same on threads
    got = []
    with pytest.raises(ValueError, match="item 13"):
        got.extend(ordered_map(_square_or_fail, range(30), 3, chunk=4))


def test_read_where_reads_what_the_listing_reads(tmp_path: Path) -> None:
    files = {f"m{k}.bin": bytes([k]) * (700 + 311 * k) for k in range(5)}
    (tmp_path / "f").mkdir()
    for name, data in files.items():
        (tmp_path / "f" / name).write_bytes(data)
    for path in (_zip(tmp_path / "a.zip", files), _tar(tmp_path / "a.tar", files), tmp_path / "f"):
        with open_members(path) as members:
            assert {m.name: read_where(m.where) for m in members.members if m.where} == files
            assert all(m.read() == read_where(m.where) for m in members.members if m.where)
    with open_members(tmp_path / "a.tar.gz" if _tar(tmp_path / "a.tar.gz", files, "w:gz") else None) as members:
        assert all(m.where is None for m in members.members)  # spooled: only this process can read them
    with open_members(tmp_path / "a.zip") as members:
        where = members.members[0].where
    _zip(tmp_path / "a.zip", {"other": b"x"})  # replaced after the listing
    with pytest.raises(InputError, match="changed after the archive was listed"):
        read_where(where)  # type: ignore[arg-type]


def _load_forked(path: str, conn: Any) -> None:
    ran, vol = load_counting_pools(path)
    conn.send((ran, vol.data.tolist()))


def test_a_forked_child_starts_its_own_fork_server(tmp_path: Path) -> None:
    """A process forked after a load (a Celery pool child, a MeshLab pool child) cannot use its parent's fork
    server; it starts its own (``engine.io.procs._forget_fork_server``)."""
    path = _zip(tmp_path / "d.zip", series(_field, positions_mm=POSITIONS))
    serial = load_volume(path, threads=1)
    load_volume(path, threads=2, processes=True)  # this process's fork server runs now
    ctx = multiprocessing.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_load_forked, args=(str(path), send))
    child.start()
    try:
        ran, data = recv.recv()
    finally:
        child.join(30)
        recv.close()
        send.close()
    assert ran == [2]
    np.testing.assert_array_equal(np.array(data, dtype=serial.data.dtype), serial.data)
