"""The PACS test environment shared by the PACS test modules: a real Orthanc (with the DICOMweb plugin), a
DICOMweb gateway in front of it (:mod:`tests.service.dicomweb_gate`), redis, the API, a Celery worker and
``bonemesh pacs``; started by the first PACS test module and stopped after the last (:func:`shared_pacs`). Plus
the helpers the tests share: generated series, a C-STORE SCU, waiting for a delivery, the model in Orthanc.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pydicom
import pytest
from pydicom.uid import generate_uid

from engine.export.dicom_stl import ENCAPSULATED_STL_STORAGE, stl_of
from engine.export.stl import from_stl
from tests.engine.dicom_factory import series
from tests.service.dicomweb_gate import DicomwebGate
from tests.service.orthanc import AE_TITLE as ORTHANC_AE
from tests.service.orthanc import OrthancServer
from tests.service.procs import (
    API_KEYS,
    Proc,
    ProcessError,
    RedisServer,
    ServiceStack,
    bonemesh_argv,
    free_port,
    wait_for_job,
    wait_until,
)

PACS_AE = "BONEMESH"
SCU_AE = "STORESCU"
STABLE_SECONDS = 2.0
ORIGIN = np.array([-140.0, -160.0, -420.0])
SHAPE = (24, 36, 36)  # z, y, x
SPACING = (1.0, 0.8, 0.8)


RETRY = {"attempts": 3, "backoff_seconds": 0.05}  # the worker's DICOMweb retries, short for the tests


class Pacs:
    """The processes: Orthanc, the DICOMweb gateway in front of it, the stack, ``bonemesh pacs``.

    The worker knows two DICOMweb servers: ``orthanc`` and ``gate`` (Orthanc behind :attr:`gate`).
    """

    def __init__(self, root: Path) -> None:
        self.port = free_port()
        self.orthanc = OrthancServer(root / "orthanc", modalities={"bonemesh": (PACS_AE, self.port)})
        self.gate = DicomwebGate(self.orthanc.dicomweb_url)
        servers = {"orthanc": {"url": self.orthanc.dicomweb_url, **RETRY}, "gate": {"url": self.gate.url, **RETRY}}
        self.redis = RedisServer(root / "redis")
        env = {
            "BONEMESH_PACS_AE_TITLE": PACS_AE,
            "BONEMESH_PACS_HOST": "127.0.0.1",
            "BONEMESH_PACS_PORT": str(self.port),
            "BONEMESH_PACS_ALLOW": f"{SCU_AE},{ORTHANC_AE}@127.0.0.1",
            "BONEMESH_PACS_STABLE_SECONDS": str(STABLE_SECONDS),
            "BONEMESH_PACS_ROUTES": json.dumps(
                [
                    # a series described "no model" is taken by no rule (a CT kept for a SEG drawn on it)
                    {"name": "bone", "min_slices": 10, "series_description": "^(?!.*no model)", "params": {}},
                    {"name": "segments", "modality": "SEG", "min_slices": 2},
                ]
            ),
            "BONEMESH_PACS_REFERENCE_WAIT_SECONDS": "4",  # a received SEG's wait for its CT series
            "BONEMESH_PACS_DESTINATION": json.dumps(
                {"kind": "dicom", "ae_title": ORTHANC_AE, "host": "127.0.0.1", "port": self.orthanc.dicom_port}
            ),
            "BONEMESH_PACS_DICOMWEB_SERVERS": json.dumps(servers),
            "BONEMESH_PACS_DELIVERY_BACKOFF_SECONDS": "0.5",
            "BONEMESH_PACS_DELIVERY_MAX_BACKOFF_SECONDS": "2",
            "BONEMESH_PACS_POLL_SECONDS": "0.3",
            "BONEMESH_PACS_OWNER_KEY": API_KEYS[0],
        }
        self.stack = ServiceStack(root / "stack", self.redis.url, extra_env=env)
        self.stack.start_server()
        self.stack.start_worker()
        self.gateway = Proc(
            "pacs", [*bonemesh_argv(), "pacs"], self.stack.log_dir / "pacs.log", self.stack.env, cwd=self.stack.root
        )
        self.stack.workers.append(self.gateway)  # its log with the others', checked alive while waiting
        wait_until(lambda: "listening on" in self.gateway.tail() or not self.gateway.alive(), 60, "bonemesh pacs")
        if not self.gateway.alive():
            raise ProcessError(f"bonemesh pacs exited at start:\n{self.gateway.tail()}")

    def close(self) -> None:
        self.stack.close()
        self.redis.close()
        self.gate.close()
        self.orthanc.close()

    def logs_text(self) -> str:
        return "\n".join(p.log.read_text(errors="replace") for p in [*self.stack.servers, *self.stack.workers])


_SHARED: dict[str, Pacs] = {}


def shared_pacs(request: pytest.FixtureRequest) -> Pacs:
    """The one :class:`Pacs` of the PACS test modules, for a module-scoped ``pacs`` fixture (``request``): started by
    the first module that uses it, stopped after the last one (no later test of the session needs ``pacs``), so
    the modules share its start and its worker's warm-up without keeping it through the rest of the session."""
    env = _SHARED.get("pacs")
    if env is None:
        try:
            env = Pacs(request.getfixturevalue("tmp_path_factory").mktemp("pacs"))
        except ProcessError as exc:
            pytest.fail(str(exc), pytrace=False)
        _SHARED["pacs"] = env
        request.config.add_cleanup(_stop)  # an interrupted session
    items = request.session.items
    mine = [k for k, item in enumerate(items) if getattr(item, "module", None) is request.module]
    if not any("pacs" in item.fixturenames for item in items[max(mine, default=len(items)) + 1 :]):
        request.addfinalizer(_stop)
    return env


def _stop() -> None:
    env = _SHARED.pop("pacs", None)
    if env is not None:
        env.close()


# -- helpers ----------------------------------------------------------------------------------------------------
def generated_series(**kwargs: Any) -> tuple[list[bytes], str, str]:
    """A small CT series (a 1000 HU ball in a water cylinder, in air) far from the origin; files, study, series."""
    nz, ny, nx = SHAPE
    dz, dy, dx = SPACING
    centre = ORIGIN + np.array([(nx - 1) * dx, (ny - 1) * dy, (nz - 1) * dz]) / 2

    def hu(p: np.ndarray) -> np.ndarray:
        body = np.linalg.norm((p - centre)[..., :2], axis=-1) < 12.0
        ball = np.linalg.norm(p - centre, axis=-1) < 7.0
        return np.where(ball, 1000.0, np.where(body, 0.0, -1000.0))

    study, series_uid = generate_uid(), generate_uid()
    files = series(
        hu,
        positions_mm=[k * dz for k in range(nz)],
        shape=(ny, nx),
        pixel_spacing=(dy, dx),
        origin=ORIGIN,
        series_uid=series_uid,
        study_uid=study,
        **kwargs,
    )
    return list(files.values()), study, series_uid


def c_store(files: list[bytes], port: int, calling: str = SCU_AE, sop_class: str | None = None) -> Any:
    """Send files with a pynetdicom C-STORE SCU; the statuses, or the association when it was not established."""
    from pynetdicom import AE

    datasets = [pydicom.dcmread(io.BytesIO(f)) for f in files]
    ae = AE(ae_title=calling)
    for ds in datasets[:1]:
        ae.add_requested_context(sop_class or ds.SOPClassUID, ds.file_meta.TransferSyntaxUID)
    assoc = ae.associate("127.0.0.1", port, ae_title=PACS_AE)
    if not assoc.is_established:
        return assoc
    try:
        return [int(assoc.send_c_store(ds).Status) for ds in datasets]
    finally:
        assoc.release()


def jobs_of_series(client: httpx.Client, series_uid: str) -> list[dict[str, Any]]:
    items = client.get("/v1/jobs", params={"limit": 200}).json()["items"]
    return [j for j in items if (j.get("source") or {}).get("series_uid") == series_uid]


def wait_delivered(pacs: Pacs, client: httpx.Client, job_id: str, timeout: float = 300) -> dict[str, Any]:
    def done(job: dict[str, Any]) -> bool:
        return job["state"] in ("failed", "cancelled") or (job.get("delivery") or {}).get("state") in (
            "delivered",
            "failed",
        )

    job = wait_for_job(client, job_id, stack=pacs.stack, timeout=timeout, until=done)
    assert job["state"] == "succeeded", json.dumps(job)
    assert job["delivery"]["state"] == "delivered", json.dumps(job)
    return job


def download(job: dict[str, Any], name: str) -> bytes:
    (out,) = [o for o in job["outputs"] if o["name"] == name]
    resp = httpx.get(out["url"], timeout=60)
    assert resp.status_code == 200, resp.text
    return resp.content


def check_model_in_orthanc(pacs: Pacs, job: dict[str, Any], study: str) -> pydicom.Dataset:
    """The Encapsulated STL is in Orthanc in the source's study and decodes to the job's model.stl."""
    found = [pydicom.dcmread(io.BytesIO(b)) for b in pacs.orthanc.instances_of(study, "M3D")]
    mine = [ds for ds in found if ds.SeriesInstanceUID == job["delivery"]["series_instance_uid"]]
    assert len(mine) == 1, [ds.SeriesInstanceUID for ds in found]
    ds = mine[0]
    assert ds.SOPClassUID == ENCAPSULATED_STL_STORAGE and ds.Modality == "M3D"
    assert ds.StudyInstanceUID == study
    assert ds.MeasurementUnitsCodeSequence[0].CodeValue == "mm"
    got_v, got_f = from_stl(stl_of(ds.to_bytes() if hasattr(ds, "to_bytes") else _bytes(ds)))
    want_v, want_f = from_stl(download(job, "model.stl"))
    np.testing.assert_allclose(got_v, want_v, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(got_f, want_f)
    return ds


def _bytes(ds: pydicom.Dataset) -> bytes:
    buf = io.BytesIO()
    ds.save_as(buf, enforce_file_format=True)
    return buf.getvalue()


def assert_no_patient_data(pacs: Pacs, job: dict[str, Any], identity: dict[str, str]) -> None:
    texts = {name: download(job, name) for name in ("report.json", "phone.glb", "ar.glb")}
    texts["logs"] = pacs.logs_text().encode()
    texts["job"] = json.dumps(job).encode()
    for what, data in texts.items():
        for key, value in identity.items():
            if value:
                assert value.encode() not in data, f"{key} appears in {what}"
