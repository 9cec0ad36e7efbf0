"""Fixtures of the service tests: a real redis-server, real ``bonemesh serve`` / ``bonemesh worker`` processes, and
small archives (the bundled headsq scan, real scans from ../shared/data, hostile and broken uploads).

The session ``stack`` (redis + API server + one CPU worker) serves most tests; tests that kill a worker or restart
Redis build their own with ``make_stack``. When a test fails, the tails of every process log are attached to its
report.
"""

from __future__ import annotations

import contextlib
import io
import json
import tarfile
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx
import numpy as np
import pytest

if TYPE_CHECKING:
    from fastapi.testclient import TestClient

from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from tests.conftest import SHARED_DATA, real_server
from tests.service.postgres import PostgresServer, PostgresUnavailable
from tests.service.procs import (
    API_KEYS,
    ProcessError,
    RedisServer,
    ServiceStack,
    submit,
    wait_for_job,
)

_OPEN_STACKS: list[ServiceStack] = []


# -- scans ------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Scan:
    """An upload with the job parameters that suit it and what the model should look like."""

    name: str
    path: Path
    params: dict[str, Any]
    shape_zyx: tuple[int, int, int]
    spacing_zyx_mm: tuple[float, float, float]
    extra: dict[str, Any] = field(default_factory=dict)


HEADSQ = Scan(
    "headsq", HEADSQ_ZIP, {"iso": 1150, "spacing": list(HEADSQ_SPACING_ZYX_MM)}, (93, 64, 64), HEADSQ_SPACING_ZYX_MM
)
CRANIUM_SPACING = (1.5, 0.9570312, 0.9570312)
SHARED_SCANS = {
    "cranium": (
        ("cranium_ct", "cranium_ct_png16.zip"),
        {"preset": "bone", "hu_offset": 1024, "spacing": list(CRANIUM_SPACING)},
        (108, 256, 256),
        CRANIUM_SPACING,
    ),
    "head_phantom_dicom": (
        ("head_phantom_dicom", "head_phantom_dicom.zip"),
        {"preset": "bone"},  # DICOM carries HU and the voxel size
        (28, 512, 512),
        (5.0, 0.451171875, 0.451171875),
    ),
}


# a synthetic CT series placed as real ones are, far from the patient frame's origin (so an STL in the grid's
# coordinates and one at the patient position cannot both pass): a 1000 HU ball in a water cylinder (the body) in
# air, stored as HU + 1024
SYNTHETIC_DICOM_ORIGIN_LPS = (-140.0, -160.0, -420.0)
SYNTHETIC_DICOM_SHAPE = (30, 40, 40)
SYNTHETIC_DICOM_SPACING = (1.0, 0.8, 0.8)


def synthetic_dicom_scan(folder: Path) -> Scan:
    """A zip of a synthetic axial CT series (no patient data; ``tests.engine.dicom_factory``), written in ``folder``."""
    from tests.engine.dicom_factory import series

    nz, ny, nx = SYNTHETIC_DICOM_SHAPE
    dz, dy, dx = SYNTHETIC_DICOM_SPACING
    origin = np.array(SYNTHETIC_DICOM_ORIGIN_LPS)
    centre = origin + np.array([(nx - 1) * dx, (ny - 1) * dy, (nz - 1) * dz]) / 2

    def hu(p: np.ndarray) -> np.ndarray:
        body = np.linalg.norm((p - centre)[..., :2], axis=-1) < 13.0
        ball = np.linalg.norm(p - centre, axis=-1) < 8.0
        return np.where(ball, 1000.0, np.where(body, 0.0, -1000.0))

    files = series(hu, positions_mm=[k * dz for k in range(nz)], shape=(ny, nx), pixel_spacing=(dy, dx), origin=origin)
    path = folder / "synthetic_ct.zip"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in files.items():
            zf.writestr(f"DICOM/{name}", data)
    return Scan("synthetic_dicom", path, {"preset": "bone"}, SYNTHETIC_DICOM_SHAPE, SYNTHETIC_DICOM_SPACING)


def shared_scan(name: str) -> Scan | None:
    """A real scan from ../shared/data, or None when the folder is absent."""
    parts, params, shape, spacing = SHARED_SCANS[name]
    path = SHARED_DATA.joinpath(*parts)
    return Scan(name, path, params, shape, spacing) if path.exists() else None


# -- processes --------------------------------------------------------------------------------------------------
@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[Any]:
    report = yield
    if report.failed and _OPEN_STACKS:
        for stack in _OPEN_STACKS:
            report.sections.append((f"service logs ({stack.root.name})", stack.logs(8000)))
    return report


def _fail_on_process_error(fn: Callable[[], Any]) -> Any:
    try:
        return fn()
    except ProcessError as exc:
        pytest.fail(str(exc), pytrace=False)


@pytest.fixture(scope="session")
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RedisServer]:
    """A redis-server on a free loopback port for the session stack (installed with apt-get when missing)."""
    server = _fail_on_process_error(lambda: RedisServer(tmp_path_factory.mktemp("redis")))
    yield server
    server.close()


class StackFactory:
    """Builds isolated stacks (their own redis-server, data folder and queue), all closed at teardown."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.made: list[tuple[RedisServer, ServiceStack]] = []

    def __call__(self, *, server: bool = True, workers: int = 1, **kwargs: Any) -> tuple[RedisServer, ServiceStack]:
        n = len(self.made) + 1
        redis = _fail_on_process_error(lambda: RedisServer(self.root / f"redis-{n}"))
        stack = ServiceStack(self.root / f"stack-{n}", redis.url, **kwargs)
        self.made.append((redis, stack))
        _OPEN_STACKS.append(stack)
        if server:
            _fail_on_process_error(stack.start_server)
        for _ in range(workers):
            stack.start_worker()
        return redis, stack

    def close(self) -> None:
        for redis, stack in self.made:
            stack.close()
            redis.close()
            if stack in _OPEN_STACKS:
                _OPEN_STACKS.remove(stack)


@pytest.fixture(scope="session")
def stack(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceStack]:
    """The shared stack: API server + one CPU worker on the session redis-server."""
    svc = ServiceStack(
        tmp_path_factory.mktemp("stack"),
        redis_server.url,
        extra_env={  # webhooks to a receiver on loopback (tests only), retried fast
            "BONEMESH_WEBHOOK_ALLOW_PRIVATE": "true",
            "BONEMESH_WEBHOOK_BACKOFF_SECONDS": "0.5",
            "BONEMESH_WEBHOOK_POLL_SECONDS": "0.2",
            "BONEMESH_WEBHOOK_RETRY_SECONDS": "30",
        },
    )
    _OPEN_STACKS.append(svc)
    try:
        _fail_on_process_error(svc.start_server)
        svc.start_worker()
        yield svc
    finally:
        svc.close()
        _OPEN_STACKS.remove(svc)


@pytest.fixture
def make_stack(tmp_path: Path) -> Iterator[StackFactory]:
    """``make_stack(server=True, workers=1, **ServiceStack kwargs) -> (redis, stack)``, isolated from the others."""
    factory = StackFactory(tmp_path)
    yield factory
    factory.close()


@pytest.fixture(scope="session")
def client_a(stack: ServiceStack) -> Iterator[httpx.Client]:
    with stack.client(API_KEYS[0]) as client:
        yield client


@pytest.fixture(scope="session")
def client_b(stack: ServiceStack) -> Iterator[httpx.Client]:
    with stack.client(API_KEYS[1]) as client:
        yield client


@pytest.fixture(scope="session")
def anon(stack: ServiceStack) -> Iterator[httpx.Client]:
    """No API key (signed links, health checks)."""
    with stack.client(None) as client:
        yield client


@pytest.fixture(scope="session")
def headsq_job(stack: ServiceStack, client_a: httpx.Client) -> dict[str, Any]:
    """A succeeded job of key-a on the bundled headsq scan (as its owner last saw it)."""
    resp = submit(client_a, HEADSQ.path, HEADSQ.params)
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=300)
    assert job["state"] == "succeeded", json.dumps(job)
    return job


# -- databases --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    """A real PostgreSQL for the session (Debian's package, installed when missing); skipped where it cannot be
    installed, except in CI, which must run these tests."""
    server = real_server(PostgresServer, PostgresUnavailable, "the database tests on PostgreSQL too")
    yield server
    server.close()


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """The URL of a new, empty database: a SQLite file, or a database of its own on the session's PostgreSQL
    (dropped after the test). Close every ``Database`` opened on it (``Database.close``)."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'jobs.db'}"
        return
    server: PostgresServer = request.getfixturevalue("postgres_server")
    url = server.create_database()
    yield url
    server.drop_database(url)


# -- archives ---------------------------------------------------------------------------------------------------
def png_bytes(image: np.ndarray) -> bytes:
    """One 8- or 16-bit grayscale PNG."""
    import imageio.v3 as iio

    return bytes(iio.imwrite("<bytes>", image, extension=".png"))


def sphere_volume(shape: tuple[int, int, int] = (16, 32, 32), radius: float = 0.35) -> np.ndarray:
    """uint16 ball (1000 inside, 0 outside) with a soft edge."""
    grids = np.meshgrid(*[np.linspace(-0.5, 0.5, n) for n in shape], indexing="ij")
    r = np.sqrt(sum(g * g for g in grids))
    return (np.clip((radius - r) * 40 + 0.5, 0, 1) * 1000).astype(np.uint16)


def slice_zip(volume: np.ndarray, prefix: str = "slices/slice_") -> bytes:
    """A zip of one PNG per z plane, in natural name order."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for z, plane in enumerate(volume):
            zf.writestr(f"{prefix}{z:04d}.png", png_bytes(plane))
    return buf.getvalue()


def zip_to_tar_gz(zip_path: Path) -> bytes:
    """The same members, repacked as a tar.gz."""
    buf = io.BytesIO()
    with zipfile.ZipFile(zip_path) as zf, tarfile.open(fileobj=buf, mode="w:gz") as tf:
        for info in zf.infolist():
            if info.is_dir():
                continue
            data = zf.read(info)
            member = tarfile.TarInfo(info.filename)
            member.size = len(data)
            tf.addfile(member, io.BytesIO(data))
    return buf.getvalue()


def zip_bomb(megabytes: int = 256) -> bytes:
    """One 'PNG' member that inflates to ``megabytes`` MB of zeros (~1000:1)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        with zf.open("slices/slice_0000.png", "w", force_zip64=True) as fh:
            fh.write(b"\x89PNG\r\n\x1a\n")
            chunk = bytes(1 << 20)
            for _ in range(megabytes):
                fh.write(chunk)
    return buf.getvalue()


def bomb_of_small_members(count: int = 300) -> bytes:
    """``count`` members of 1 MiB of zeros behind a PNG signature: each is at the per-member ratio floor (not
    ratio-checked alone), together they expand about 1000x."""
    buf = io.BytesIO()
    member = b"\x89PNG\r\n\x1a\n" + bytes((1 << 20) - 8)
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for i in range(count):
            zf.writestr(f"slices/slice_{i:04d}.png", member)
    return buf.getvalue()


def traversal_zip(style: str) -> bytes:
    """Valid PNG slices under hostile names: ``dotdot``, ``absolute`` or ``backslash``."""
    prefix = {
        "dotdot": "../../../../tmp/bonemesh_evil_",
        "absolute": "/etc/bonemesh_evil_",
        "backslash": "..\\..\\evil_",
    }
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for z, plane in enumerate(sphere_volume((8, 16, 16))):
            info = zipfile.ZipInfo("placeholder")
            info.filename = f"{prefix[style]}{z:04d}.png"  # set after construction: ZipInfo would clean it
            zf.writestr(info, png_bytes(plane))
    return buf.getvalue()


def hostile_tar(kind: str) -> bytes:
    """A tar.gz with a ``dotdot`` member name or a ``symlink`` member pointing out of the archive."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        for z, plane in enumerate(sphere_volume((8, 16, 16))):
            data = png_bytes(plane)
            name = f"../../tmp/bonemesh_evil_{z:04d}.png" if kind == "dotdot" else f"slices/slice_{z:04d}.png"
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
        if kind == "symlink":
            link = tarfile.TarInfo("slices/slice_9999.png")
            link.type = tarfile.SYMTYPE
            link.linkname = "/etc/passwd"
            tf.addfile(link)
    return buf.getvalue()


def many_members_zip(count: int = 30_000) -> bytes:
    """A zip with ``count`` one-byte members (more than any sane slice stack)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for i in range(count):
            zf.writestr(f"s/{i:06d}.png", b"x")
    return buf.getvalue()


def no_images_zip() -> bytes:
    """A well-formed zip holding only text."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("README.txt", "these are not the slices you are looking for\n")
        zf.writestr("notes/data.csv", "z,y,x\n1,2,3\n")
    return buf.getvalue()


def mixed_sizes_zip() -> bytes:
    """PNG slices of two different sizes (seen only when loading)."""
    vol = sphere_volume((10, 32, 32))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for z, plane in enumerate(vol):
            image = plane if z != 6 else np.pad(plane, ((0, 8), (0, 0)))
            zf.writestr(f"slices/slice_{z:04d}.png", png_bytes(image))
    return buf.getvalue()


def corrupt_member_zip() -> bytes:
    """A slice stack in which one PNG is cut short."""
    vol = sphere_volume((10, 32, 32))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for z, plane in enumerate(vol):
            data = png_bytes(plane)
            zf.writestr(f"slices/slice_{z:04d}.png", data if z != 4 else data[: len(data) // 2])
    return buf.getvalue()


@pytest.fixture(scope="session")
def long_scan(tmp_path_factory: pytest.TempPathFactory) -> Scan:
    """A scan whose job runs well over 5 s on the CPU: the cranium when present, else a generated bone phantom."""
    scan = shared_scan("cranium")
    if scan is not None:
        return scan
    from benchmarks.phantom import BONE_LEVEL, bone_phantom

    shape = (160, 256, 256)
    path = tmp_path_factory.mktemp("phantom") / "phantom_160x256x256.zip"
    path.write_bytes(slice_zip(bone_phantom(shape), prefix="phantom/phantom_"))
    spacing = (0.5, 0.5, 0.5)
    return Scan("phantom", path, {"iso": BONE_LEVEL, "spacing": list(spacing)}, shape, spacing)


@contextlib.contextmanager
def app_client(data_dir: Path, max_upload_bytes: int = 8 << 20, **settings: Any) -> Iterator[TestClient]:
    """The API in-process (FastAPI's test client) with two keys and a broker address nothing listens on: an
    accepted job stays queued. ``settings``: more of its settings (``core.settings.Settings`` fields)."""
    from fastapi.testclient import TestClient

    from core.settings import Settings
    from service.app import create_app

    config = Settings(
        data_dir=data_dir,
        api_keys=["key-a", "key-b"],
        secret_key="s" * 32,
        redis_url="redis://127.0.0.1:1/0",
        max_upload_bytes=max_upload_bytes,
        reconcile_seconds=3600,
        **settings,
    )
    with TestClient(create_app(config)) as c:
        yield c


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with app_client(tmp_path) as c:
        yield c


# -- the PACS environment (tests.service.pacs_env), one for the PACS test modules --------------------------------
@pytest.fixture(scope="module")
def pacs(request: pytest.FixtureRequest) -> Any:
    """The shared PACS environment (``tests.service.pacs_env.shared_pacs``: started by the first module using it,
    stopped after the last)."""
    from tests.service.pacs_env import shared_pacs

    return shared_pacs(request)


@pytest.fixture(scope="module")
def pacs_client(pacs: Any) -> Iterator[httpx.Client]:
    """A client of the PACS environment's API with the first API key."""
    with pacs.stack.client(API_KEYS[0]) as c:
        yield c


# -- the page in a real browser (tests marked ``browser``) -----------------------------------------------------
@pytest.fixture(scope="module")
def chromium_paths() -> tuple[str, str]:
    """Debian's Chromium and its driver (skipped, with the reason, where they cannot be installed)."""
    from tests.service.browser import find_chromium

    paths = find_chromium()
    if isinstance(paths, str):
        pytest.skip(paths)
    return paths


@pytest.fixture(scope="module")
def artefacts(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Where the browser tests keep their screenshots (printed by the tests that write them)."""
    folder = tmp_path_factory.getbasetemp() / "artefacts"
    folder.mkdir(exist_ok=True)
    return folder
