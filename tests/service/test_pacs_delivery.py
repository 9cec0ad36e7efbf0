"""Traceable deliveries: the Encapsulated STL references the source series and exactly the images the model was
built from, is made only from a series checked complete, and ``POST /v1/jobs/{id}/deliver`` queues a finished
job's model again (same UIDs; idempotent; the usual auth)."""

from __future__ import annotations

import contextlib
import io
import zipfile
from pathlib import Path

import numpy as np
import pydicom
import pytest

from core.db import Database, Job, owner_of, utcnow
from core.pacs.records import PacsRecords
from core.storage import LocalStorage
from engine.errors import IncompleteSeriesError
from engine.export.dicom_stl import ENCAPSULATED_STL_STORAGE
from engine.io import load_volume
from tests.engine.dicom_factory import series
from tests.service.conftest import app_client


def _ball(p: np.ndarray) -> np.ndarray:
    return np.where(np.linalg.norm(p - np.array([0.0, 0.0, 5.0]), axis=-1) < 4.0, 1000.0, -1000.0)


def _pacs_job(db: Database, state: str = "succeeded", dest: bool = True, owner: str = "o") -> Job:
    job = Job(id=Database.new_id(), owner=owner, state=state, params={}, upload_name="series")
    destination = {"kind": "dicom", "ae_title": "PACS", "host": "127.0.0.1", "port": 104} if dest else None
    PacsRecords(db).create_job(job, {"kind": "dimse", "series_uid": "1.2.3"}, destination)
    return job


def test_redeliver_states(tmp_path: Path, db_url: str) -> None:
    with contextlib.closing(Database(db_url)) as db:
        records = PacsRecords(db)
        job = _pacs_job(db)
        assert records.redeliver(job.id) is True  # still waiting: left as it is
        assert records.get(job.id).delivery_state == "waiting"  # type: ignore[union-attr]
        for state in ("delivered", "failed", "retrying"):
            records.claim(job.id, utcnow())
            if state == "delivered":
                records.delivered(job.id)
            else:
                records.failed_attempt(job.id, "no route", None if state == "failed" else utcnow())
            assert records.get(job.id).delivery_state == state  # type: ignore[union-attr]
            assert records.redeliver(job.id) is True
            rec = records.get(job.id)
            assert rec is not None and rec.delivery_state == "waiting" and rec.delivery_attempts == 0
            assert rec.delivery_error is None and rec.next_attempt_at is None
        none = _pacs_job(db, dest=False)
        assert records.redeliver(none.id) is False and records.get(none.id).delivery_state == "none"  # type: ignore[union-attr]


def test_deliver_route(tmp_path: Path) -> None:
    data = tmp_path / "data"
    with app_client(data) as client:
        db = client.app.state.services.db  # type: ignore[attr-defined]
        owner = owner_of("key-a")
        storage = LocalStorage(data)
        done = _pacs_job(db, owner=owner)
        staged = storage.staging_dir(done.id)
        (staged / "model.dcm").write_bytes(b"DICM")
        storage.publish(done.id, staged)
        PacsRecords(db).claim(done.id, utcnow())
        PacsRecords(db).delivered(done.id)
        a = {"X-API-Key": "key-a"}
        resp = client.post(f"/v1/jobs/{done.id}/deliver", headers=a)
        assert resp.status_code == 202, resp.text
        delivery = resp.json()["delivery"]
        assert delivery["state"] == "waiting" and delivery["attempts"] == 0
        again = client.post(f"/v1/jobs/{done.id}/deliver", headers=a)
        assert again.status_code == 202 and again.json()["delivery"] == delivery  # idempotent: the same UIDs
        assert client.post(f"/v1/jobs/{done.id}/deliver").status_code == 401
        assert client.post(f"/v1/jobs/{done.id}/deliver", headers={"X-API-Key": "key-b"}).status_code == 404
        running = _pacs_job(db, state="running", owner=owner)
        resp = client.post(f"/v1/jobs/{running.id}/deliver", headers=a)
        assert resp.status_code == 409 and "only a succeeded job" in resp.json()["detail"]
        no_model = _pacs_job(db, owner=owner)
        resp = client.post(f"/v1/jobs/{no_model.id}/deliver", headers=a)
        assert resp.status_code == 409 and "no model.dcm" in resp.json()["detail"]
        nowhere = _pacs_job(db, dest=False, owner=owner)
        staged = storage.staging_dir(nowhere.id)
        (staged / "model.dcm").write_bytes(b"DICM")
        storage.publish(nowhere.id, staged)
        resp = client.post(f"/v1/jobs/{nowhere.id}/deliver", headers=a)
        assert resp.status_code == 409 and "no PACS destination" in resp.json()["detail"]


def test_model_references_exactly_the_images_used(tmp_path: Path) -> None:
    """The upload holds the series (one image sent twice) and an image of another series: the object references
    the series and its 9 distinct images, nothing else."""
    from engine.job.outputs import write_outputs
    from engine.params import ReconParams
    from engine.job.pipeline import reconstruct
    from worker.pacs import UncheckedSource, write_dicom_model

    files = series(_ball, positions_mm=[float(k) for k in range(9)], shape=(24, 24), origin=(-6, -6, 0))
    uid = pydicom.dcmread(io.BytesIO(files["IM1"])).SeriesInstanceUID
    upload = tmp_path / "upload"
    upload.mkdir()
    for name, data in files.items():
        (upload / f"{name}.dcm").write_bytes(data)
    (upload / "copy-of-IM4.dcm").write_bytes(files["IM4"])
    (upload / "other.dcm").write_bytes(series(_ball, positions_mm=[0.0], shape=(24, 24))["IM1"])
    vol = load_volume(upload, series_uid=str(uid))
    assert vol.source["completeness"]["duplicates_dropped"] == 1
    params = ReconParams.from_dict({"iso": {"preset": "bone"}, "body": None})
    staged = tmp_path / "staged"
    write_outputs(reconstruct(vol, params, device="cpu"), staged, params, device="cpu")
    with contextlib.closing(Database(f"sqlite:///{tmp_path / 'j.db'}")) as db:
        job = _pacs_job(db)
        paths = write_dicom_model(db, job.id, upload, staged, vol)
        ds = pydicom.dcmread(paths["model.dcm"])
        assert ds.SOPClassUID == ENCAPSULATED_STL_STORAGE
        want = {pydicom.dcmread(io.BytesIO(b)).SOPInstanceUID for b in files.values()}
        assert {r.ReferencedSOPInstanceUID for r in ds.SourceInstanceSequence} == want
        assert len(ds.SourceInstanceSequence) == 9
        (ref,) = ds.ReferencedSeriesSequence
        assert ref.SeriesInstanceUID == uid and {r.ReferencedSOPInstanceUID for r in ref.ReferencedInstanceSequence} == want
        unchecked = type(vol)(data=vol.data, spacing_zyx_mm=vol.spacing_zyx_mm, source={"format": "dicom"})
        with pytest.raises(UncheckedSource, match="not checked complete"):
            write_dicom_model(db, job.id, upload, staged, unchecked)


def test_an_incomplete_upload_fails_the_job_with_the_reason(tmp_path: Path) -> None:
    from worker.tasks import _explain

    files = series(_ball, positions_mm=[float(k) for k in range(6)], shape=(16, 16))
    del files["IM3"]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    path = tmp_path / "holed.zip"
    path.write_bytes(buf.getvalue())
    with pytest.raises(IncompleteSeriesError) as err:
        load_volume(path)
    code, message = _explain(err.value, "scan.zip")
    assert code == "incomplete_series"
    assert "1 slice(s) missing between IM2 and IM4" in message and "Nothing was reconstructed" in message
