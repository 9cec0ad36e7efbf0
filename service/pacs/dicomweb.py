"""Clients of the configured DICOMweb servers (dicomweb-client): credentials come from the settings only."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from service.pacs.config import DicomwebServer

EXTRA = "bonemesh[pacs]"


def client_for(server: DicomwebServer) -> Any:
    """A ``dicomweb_client.DICOMwebClient`` for a configured server (basic auth or bearer token from the settings).

    Raises:
        ImportError: dicomweb-client is not installed (the message names the extra).
    """
    try:
        import requests
        from dicomweb_client.api import DICOMwebClient
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ImportError(f"DICOMweb needs dicomweb-client: pip install '{EXTRA}'") from exc
    session = requests.Session()
    if server.username is not None:
        session.auth = (server.username, server.password.get_secret_value() if server.password else "")
    if server.token is not None:
        session.headers["Authorization"] = f"Bearer {server.token.get_secret_value()}"
    return DICOMwebClient(url=server.url.rstrip("/"), session=session, timeout=server.timeout_seconds)


def fetch_series(server: DicomwebServer, study_uid: str, series_uid: str, folder: Path) -> int:
    """Retrieve a series with WADO-RS into ``folder`` (one Part 10 file per instance); returns the instance count.

    Raises:
        requests.HTTPError, requests.ConnectionError: the server refused or could not be reached.
    """
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian

    client = client_for(server)
    folder.mkdir(parents=True, exist_ok=True)
    count = 0
    for count, ds in enumerate(client.iter_series(study_uid, series_uid), start=1):
        if not getattr(ds, "file_meta", None) or "TransferSyntaxUID" not in ds.file_meta:
            meta = FileMetaDataset()
            meta.MediaStorageSOPClassUID = ds.SOPClassUID
            meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
            meta.TransferSyntaxUID = ExplicitVRLittleEndian
            ds.file_meta = meta
        ds.save_as(folder / f"{count:06d}.dcm", enforce_file_format=True)
    return count


def store_file(server: DicomwebServer, path: Path) -> None:
    """Store one DICOM file with STOW-RS.

    Raises:
        requests.HTTPError, requests.ConnectionError: the server refused or could not be reached.
        RuntimeError: the server answered but lists the instance as failed.
    """
    import pydicom

    ds = pydicom.dcmread(path)
    response = client_for(server).store_instances([ds])
    failed = response.get("FailedSOPSequence") if response is not None else None
    if failed:
        reason = failed[0].get("FailureReason", "?")
        raise RuntimeError(f"STOW-RS: the server refused the instance (failure reason {reason})")
