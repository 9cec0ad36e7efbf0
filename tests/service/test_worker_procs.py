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
from tests.engine.decode_spy import load_counting_pools
from tests.engine.dicom_factory import series

billiard = pytest.importorskip("billiard")


def _load(path: str) -> dict[str, Any]:
    """In the billiard child: load with processes asked for; whether a pool of processes was really used."""
    used, vol = load_counting_pools(path)
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


def test_worker_loads_with_the_decode_settings(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """BONEMESH_DECODE_THREADS / _DECODE_PROCESSES / _PNG_DECODER reach load_volume (the service benchmark's
    baseline worker relies on them)."""
    from types import SimpleNamespace

    import engine.io
    import worker.tasks as tasks
    from core.settings import Settings
    from engine.io import codecs
    from engine.io.png_rows import DeviceRows, device_rows
    from engine.staging import pinned_volumes

    class Stop(Exception):
        pass

    seen: dict[str, Any] = {}

    def fake_load(path: Path, **kwargs: Any) -> None:
        seen.update(kwargs, imagecodecs=codecs.USE_IMAGECODECS)
        raise Stop

    monkeypatch.setattr(engine.io, "load_volume", fake_load)
    monkeypatch.setattr(tasks, "fetch_source", lambda *args: None)
    monkeypatch.setattr(codecs, "USE_IMAGECODECS", True)
    for name in ("BONEMESH_DECODE_THREADS", "BONEMESH_DECODE_PROCESSES", "BONEMESH_PNG_DECODER"):
        monkeypatch.delenv(name, raising=False)
    job = SimpleNamespace(id="job", engine_params={"recon": {}, "spacing_zyx_mm": [1.0, 0.5, 0.5]})
    holder = SimpleNamespace(progress=lambda *args: None)
    for settings, expected in (
        (Settings(), {"threads": None, "processes": None, "imagecodecs": True}),
        (
            Settings(decode_threads=1, decode_processes=False, png_decoder="pillow"),
            {"threads": 1, "processes": False, "imagecodecs": False},
        ),
        (Settings(png_decoder="libpng"), {"threads": None, "processes": None, "imagecodecs": True}),
    ):
        seen.clear()
        with pytest.raises(Stop):
            tasks._run(job, tmp_path / "upload.zip", tmp_path / "staged", holder, settings, None)  # type: ignore[arg-type]
        # the process's page-locked volume buffer on a CUDA device, plain arrays here
        allocate = pinned_volumes(settings.device)
        assert callable(seen.pop("on_progress"))  # the job's loading progress
        rows = seen.pop("rows")  # PNG rows unfiltered on the job's GPU (auto only); none on a CPU
        on_device = settings.png_decoder == "auto" and device_rows(settings.device) is not None
        assert isinstance(rows, DeviceRows) if on_device else rows is None
        assert seen == {"spacing_zyx_mm": (1.0, 0.5, 0.5), "allocate": allocate, "level": None, **expected}
