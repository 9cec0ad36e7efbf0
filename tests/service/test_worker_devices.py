"""A worker's device setting naming several devices (``BONEMESH_DEVICE=cuda:0,cuda:1``, docs/multi-gpu.md): its
runtime carries them all, and every job's model is split over them (``engine.job.Runtime.device``)."""

from __future__ import annotations

import pytest

from core.settings import Settings
from worker.app import runtime_of


def test_a_worker_resolves_a_device_list_from_its_settings(monkeypatch):
    monkeypatch.setenv("BONEMESH_DEVICE", "cpu,cpu")
    runtime = runtime_of(Settings())
    assert runtime.spec == "cpu,cpu" and runtime.device == (runtime.backend, runtime.backend)
    assert runtime.describe().startswith("device cpu,cpu -> warp cpu + warp cpu")


def test_a_worker_refuses_a_list_naming_an_absent_device():
    with pytest.raises(ValueError, match="'cuda:99' of the list 'cpu,cuda:99'"):
        runtime_of(Settings(device="cpu,cuda:99"))
