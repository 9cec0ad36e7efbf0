"""PACS pieces in-process: settings (no accept-everything default), routing rules, the inbox (grouping, duplicates,
stable age, re-sent series), the storage SCP's statuses, the delivery outbox's backoff and claims."""

from __future__ import annotations

import contextlib
import datetime as dt
import io
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest
from pydantic import ValidationError

from core.db import Database, Job, utcnow
from core.pacs.config import PacsSettings
from core.pacs.records import PacsRecords, result_uids
from core.pacs.routing import DEFAULT_RULES, Rule, SeriesSummary, choose_rule
from core.storage import LocalStorage
from service.pacs.delivery import Dispatcher
from service.pacs.inbox import Inbox
from tests.engine.dicom_factory import ct_slice
from tests.service.procs import free_port


def _summary(**kw: Any) -> SeriesSummary:
    args: dict[str, Any] = {"study_uid": "1.2", "series_uid": "1.3", "modality": "CT", "images": 120}
    args.update(kw)
    return SeriesSummary(**args)


def test_settings_parse_the_allow_list_and_have_no_open_default(monkeypatch: pytest.MonkeyPatch) -> None:
    assert PacsSettings().allow == []
    assert not PacsSettings().admits("ANYONE", "10.0.0.1")
    monkeypatch.setenv("BONEMESH_PACS_ALLOW", "ORTHANC, PACS1@10.0.0.5")
    monkeypatch.setenv("BONEMESH_PACS_ROUTES", json.dumps([{"name": "hips", "body_part": "PELVIS", "min_slices": 40}]))
    s = PacsSettings()
    assert s.admits("ORTHANC", "192.168.1.1") and s.admits("PACS1", "10.0.0.5")
    assert not s.admits("PACS1", "10.0.0.6") and not s.admits("OTHER", "10.0.0.5")
    assert s.routes[0].body_part == "PELVIS" and s.routes[0].params == {"preset": "bone"}
    monkeypatch.setenv("BONEMESH_PACS_DESTINATION", json.dumps({"kind": "dicomweb", "server": "nowhere"}))
    with pytest.raises(ValidationError, match="not in BONEMESH_PACS_DICOMWEB_SERVERS"):
        PacsSettings()


def test_rules_with_bad_params_or_patterns_are_refused_at_start() -> None:
    with pytest.raises(ValidationError):
        Rule(name="x", params={"reduction": 5})
    with pytest.raises(ValidationError):
        Rule(name="x", series_description="(unclosed")


@pytest.mark.parametrize(
    ("summary", "taken", "why"),
    [
        (_summary(), True, "rule 'bone'"),
        (_summary(images=3), False, "3 images, fewer than 16"),
        (_summary(modality="MR"), False, "modality MR, not CT"),
        (_summary(image_type=("ORIGINAL", "PRIMARY", "LOCALIZER")), False, "Image Type LOCALIZER"),
        (_summary(description="Topogram 0.6 T20s"), False, "scout, localizer or dose report"),
        (_summary(description="Dose Report"), False, "scout, localizer or dose report"),
    ],
)
def test_default_rule(summary: SeriesSummary, taken: bool, why: str) -> None:
    rule, reason = choose_rule(summary, DEFAULT_RULES)
    assert (rule is not None) == taken and why in reason


def test_first_matching_rule_gives_the_params() -> None:
    rules = [
        Rule(name="hips", body_part="pelvis|hip", params={"preset": "bone", "reduction": 0.1}),
        Rule(name="bone"),
    ]
    rule, _ = choose_rule(_summary(body_part="PELVIS"), rules)
    assert rule is not None and rule.name == "hips" and rule.job_params().reduction == 0.1
    rule, _ = choose_rule(_summary(body_part="HEAD"), rules)
    assert rule is not None and rule.name == "bone"


def _write(data: bytes) -> Any:
    return lambda fh: fh.write(data)


def test_inbox_groups_dedupes_and_waits_for_the_stable_age(tmp_path: Path) -> None:
    inbox = Inbox(tmp_path, stable_seconds=0.5)
    sender = {"ae_title": "X", "address": "127.0.0.1"}
    assert inbox.store("1.2", "1.2.3", "1.2.3.1", sender, _write(b"a")) is False
    assert inbox.store("1.2", "1.2.3", "1.2.3.1", sender, _write(b"b")) is True  # same SOP Instance UID: replaced
    inbox.store("1.2", "1.2.3", "1.2.3.2", sender, _write(b"c"))
    inbox.store("1.2", "1.2.4", "1.2.4.1", sender, _write(b"d"))
    assert inbox.claim_stable() == []  # too fresh
    time.sleep(0.6)
    claimed = sorted(inbox.claim_stable(), key=lambda c: c.series_uid)
    assert [(c.study_uid, c.series_uid, len(c.files())) for c in claimed] == [("1.2", "1.2.3", 2), ("1.2", "1.2.4", 1)]
    assert claimed[0].sender == sender and claimed[0].files()[0].read_bytes() == b"b"
    inbox.store("1.2", "1.2.3", "1.2.3.1", sender, _write(b"again"))  # re-sent after the claim: a new series folder
    time.sleep(0.6)
    (again,) = inbox.claim_stable()[-1:]
    assert again.folder != claimed[0].folder and len(again.files()) == 1
    with pytest.raises(ValueError, match="DICOM UID"):
        inbox.store("1.2", "../../etc", "1.2.3.1", sender, _write(b"x"))


def test_inbox_keeps_a_series_for_a_later_seg_until_it_expires(tmp_path: Path) -> None:
    inbox = Inbox(tmp_path, stable_seconds=0.05)
    sender = {"ae_title": "X", "address": "127.0.0.1"}
    for data in (b"old", b"new"):  # sent twice: the newer copy replaces the kept one
        inbox.store("1.2", "1.2.5", "1.2.5.1", sender, _write(data))
        time.sleep(0.1)
        (series,) = inbox.claim_stable()
        inbox.keep(series)
    kept = inbox.kept_series("1.2.5")
    assert kept is not None and (kept / "1.2.5.1.dcm").read_bytes() == b"new" and not series.folder.exists()
    assert inbox.kept_series("1.2.6") is None and inbox.kept_series("../1.2.5") is None
    assert inbox.expire_kept(3600) == 0 and inbox.kept_series("1.2.5") is not None
    time.sleep(0.05)
    assert inbox.expire_kept(0.01) == 1 and inbox.kept_series("1.2.5") is None


def test_scp_statuses(tmp_path: Path) -> None:
    from pynetdicom import AE

    from service.pacs.scp import StorageSCP

    settings = PacsSettings(port=free_port(), allow="SCU")  # type: ignore[arg-type]
    inbox = Inbox(tmp_path, stable_seconds=60)
    scp = StorageSCP(settings, inbox)
    scp.start()
    try:
        ct = pydicom.dcmread(
            io.BytesIO(ct_slice(np.zeros((4, 4), np.uint16), ipp=(0, 0, 0), series_uid="1.9", instance=1))
        )
        ae = AE(ae_title="SCU")
        ae.add_requested_context(ct.SOPClassUID, ct.file_meta.TransferSyntaxUID)
        assoc = ae.associate("127.0.0.1", scp.port, ae_title=settings.ae_title)
        assert assoc.is_established
        assert assoc.send_c_store(ct).Status == 0x0000
        bad = ct.copy()
        with pytest.warns(UserWarning, match="Invalid value for VR UI"):
            bad.SeriesInstanceUID = "1.2.3/../../x"  # a path, not a UID
        assert assoc.send_c_store(bad).Status == 0xC000
        assoc.release()
    finally:
        scp.stop()
    (study,) = list(inbox.incoming.iterdir())
    (series,) = list(study.iterdir())
    stored = pydicom.dcmread(next(series.glob("*.dcm")))
    assert stored.SOPInstanceUID == ct.SOPInstanceUID and stored.PatientID == ct.PatientID  # the file as sent


# pynetdicom leaves the socket of a refused connection to the garbage collector
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_delivery_backs_off_and_gives_up_visibly(tmp_path: Path, db_url: str) -> None:
    with contextlib.closing(Database(db_url)) as db:
        records = PacsRecords(db)
        storage = LocalStorage(tmp_path / "data")
        job = Job(id=Database.new_id(), owner="o", state="succeeded", params={}, upload_name="x")
        dest = {"kind": "dicom", "ae_title": "NOBODY", "host": "127.0.0.1", "port": free_port()}
        records.create_job(job, {"kind": "dimse"}, dest)
        staged = storage.staging_dir(job.id)
        (staged / "model.dcm").write_bytes(
            ct_slice(np.zeros((2, 2), np.uint16), ipp=(0, 0, 0), series_uid="1.5", instance=1)
        )
        storage.publish(job.id, staged)
        pacs = PacsSettings(delivery_backoff_seconds=10, delivery_max_backoff_seconds=25, delivery_max_attempts=3)
        dispatcher = Dispatcher(pacs, records, storage)
        assert [dispatcher.backoff(n) for n in (1, 2, 3, 4)] == [10, 20, 25, 25]
        # a DICOMweb server's Retry-After (STOW-RS 429/503) is a floor, within the longest backoff
        assert [dispatcher.backoff(1, asked) for asked in (None, 3, 17, 90)] == [10, 10, 17, 25]
        now = utcnow()
        assert dispatcher.run_once(now) == 0
        view = records.view(job)["delivery"]
        assert view["state"] == "retrying" and view["attempts"] == 1 and "NOBODY@127.0.0.1" in view["error"]
        assert dispatcher.run_once(now) == 0 and records.get(job.id).delivery_attempts == 1  # not due yet
        for k in (1, 2):
            dispatcher.run_once(now + dt.timedelta(seconds=100 * k))
        rec = records.get(job.id)
        assert rec is not None and rec.delivery_state == "failed" and rec.delivery_attempts == 3
        assert result_uids(job.id) == (rec.result_series_uid, rec.result_sop_uid)


@pytest.mark.parametrize("syntax", ["1.2.840.10008.1.2.5", "1.2.840.10008.1.2.4.90"])  # RLE, JPEG 2000 lossless
def test_scp_keeps_compressed_instances_as_sent(tmp_path: Path, syntax: str) -> None:
    from pynetdicom import AE

    from service.pacs.scp import StorageSCP

    pixels = (np.arange(64 * 64, dtype=np.uint16).reshape(64, 64) % 977) + 1000
    sent = pydicom.dcmread(
        io.BytesIO(ct_slice(pixels, ipp=(0, 0, 0), series_uid="1.7", instance=1, transfer_syntax=syntax))
    )
    scp = StorageSCP(PacsSettings(port=free_port(), allow="SCU"), Inbox(tmp_path, stable_seconds=60))  # type: ignore[arg-type]
    scp.start()
    try:
        ae = AE(ae_title="SCU")
        ae.add_requested_context(sent.SOPClassUID, syntax)
        assoc = ae.associate("127.0.0.1", scp.port, ae_title="BONEMESH")
        assert assoc.is_established
        assert assoc.send_c_store(sent).Status == 0x0000
        assoc.release()
    finally:
        scp.stop()
    (path,) = tmp_path.glob("incoming/*/*/*.dcm")
    stored = pydicom.dcmread(path)
    assert stored.file_meta.TransferSyntaxUID == syntax
    np.testing.assert_array_equal(stored.pixel_array, pixels)
