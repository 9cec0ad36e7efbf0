"""Shared fixtures: ``--device`` option (kornia style) and the ``gpu`` marker's auto-skip."""

from __future__ import annotations

import functools
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--device",
        default="cpu",
        help="device(s) for engine tests: cpu, cuda, cuda:N, or all (cpu + every CUDA device)",
    )


@functools.cache
def _cuda_devices() -> tuple[str, ...]:
    from engine.device import init_runtime

    init_runtime()
    import warp as wp

    return tuple(f"cuda:{i}" for i in range(wp.get_cuda_device_count()))


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "device" in metafunc.fixturenames:
        opt = metafunc.config.getoption("--device")
        devices = ["cpu", *_cuda_devices()] if opt == "all" else [opt]
        metafunc.parametrize("device", devices)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if _cuda_devices():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device; none is present")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


def shared_file(*parts: str) -> Path:
    """A file under ../shared/data, or skip the test with the reason."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"{path} is absent (the ../shared data checkout is not beside the repo)")
    return path
