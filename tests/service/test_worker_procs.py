"""The worker's pool child may start the engine's process pools: a billiard (Celery prefork) child prepared by
``worker.app._allow_children`` decodes a DICOM series in processes (``engine.io.procs``); one left as billiard
makes it decodes on threads. Both give the serial loop's volume."""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from engine.io import load_volume
from tests.engine.dicom_factory import series

billiard = pytest.importorskip("billiard")


def _load(path: str) -> dict[str, Any]:
    """In the billiard child: load with processes asked for; whether a pool of processes was really used."""
    import engine.io.procs as procs

    used: list[int] = []
    real = procs.DecodePool.close

    def spy(pool: procs.DecodePool) -> None:  # a pool that ran is closed; one given up at start is not
        used.append(len(pool.pool._processes or {}))  # type: ignore[attr-defined]
        real(pool)

    procs.DecodePool.close = spy  # type: ignore[method-assign]
    try:
        vol = load_volume(path, threads=2, processes=True)
    finally:
        procs.DecodePool.close = real  # type: ignore[method-assign]
    return {"pools": used, "data": vol.data.tolist(), "dtype": str(vol.data.dtype)}


def _prepare() -> None:
    from worker.app import _allow_children

    _allow_children()


@pytest.mark.parametrize("prepared", [True, False], ids=["worker-child", "plain-billiard-child"])
def test_worker_child_decodes_dicom_in_processes(tmp_path: Path, prepared: bool) -> None:
    files = series(lambda p: 3.0 * p[..., 0] - 2.0 * p[..., 1] + 10.0 * p[..., 2], positions_mm=list(range(12)))
    path = tmp_path / "d.zip"
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    serial = load_volume(path, threads=1)
    with billiard.Pool(1, initializer=_prepare if prepared else None) as pool:
        got = pool.apply(_load, (str(path),))
    assert got["dtype"] == str(serial.data.dtype)
    np.testing.assert_array_equal(np.array(got["data"], dtype=serial.data.dtype), serial.data)
    assert got["pools"] == ([2] if prepared else [])  # billiard's own child is daemonic: threads
