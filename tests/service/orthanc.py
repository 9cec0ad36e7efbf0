"""A real Orthanc (Debian's ``orthanc`` + ``orthanc-dicomweb``) for the PACS tests: generated configuration on free
loopback ports, its own storage folder, run as a subprocess (:class:`tests.service.procs.Proc`) and stopped after.

    with OrthancServer(tmp / "orthanc", modalities={"bonemesh": ("BONEMESH", 11112)}) as orthanc:
        orthanc.get("/system")

Orthanc accepts C-STORE only from the modalities named in its configuration (``DicomAlwaysAllowStore: false``).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import httpx

from tests.service.procs import Proc, ProcessError, apt_install, free_port, wait_until

PLUGIN_DIRS = ("/usr/share/orthanc/plugins", "/usr/lib/orthanc")
AE_TITLE = "ORTHANC"


def find_orthanc(install: bool = True) -> tuple[str, str]:
    """The Orthanc executable and its DICOMweb plugin, installed with apt-get (as root) when missing.

    Raises:
        ProcessError: not found and not installable here.
    """

    def found() -> tuple[str, str] | None:
        exe = shutil.which("Orthanc") or next((p for p in ("/usr/sbin/Orthanc",) if Path(p).is_file()), None)
        plugin = next((str(p) for d in PLUGIN_DIRS for p in sorted(Path(d).glob("libOrthancDicomWeb.so*"))), None)
        return (exe, plugin) if exe and plugin else None

    hit = apt_install(["orthanc", "orthanc-dicomweb"], found) if install else found()
    if hit is None:
        raise ProcessError(
            "Orthanc is not installed and could not be installed (apt-get install orthanc orthanc-dicomweb)"
        )
    return hit


class OrthancServer:
    """Orthanc with the DICOMweb plugin on free loopback ports.

    Args:
        workdir: its folder (configuration, storage, log).
        modalities: name -> (AE title, port) of DICOM nodes on 127.0.0.1 allowed to store into it.
    """

    def __init__(self, workdir: Path, modalities: dict[str, tuple[str, int]] | None = None) -> None:
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.executable, self.plugin = find_orthanc()
        self.http_port, self.dicom_port = free_port(), free_port()
        self.config = self.workdir / "orthanc.json"
        config = {
            "Name": "bonemesh-test",
            "StorageDirectory": str(self.workdir / "storage"),
            "IndexDirectory": str(self.workdir / "storage"),
            "Plugins": [self.plugin],
            "HttpServerEnabled": True,
            "HttpPort": self.http_port,
            "RemoteAccessAllowed": False,
            "AuthenticationEnabled": False,
            "DicomServerEnabled": True,
            "DicomAet": AE_TITLE,
            "DicomPort": self.dicom_port,
            "DicomAlwaysAllowStore": False,
            "DicomCheckCalledAet": False,
            "DicomModalities": {
                name: {"AET": ae, "Host": "127.0.0.1", "Port": port, "AllowStore": True}
                for name, (ae, port) in (modalities or {}).items()
            },
            "DicomWeb": {"Enable": True, "Root": "/dicom-web/", "EnableWado": True},
            "StableAge": 1,
            "SaveJobs": False,
        }
        self.config.write_text(json.dumps(config, indent=2))
        self.proc: Proc | None = None
        self.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    @property
    def dicomweb_url(self) -> str:
        return f"{self.url}/dicom-web"

    def _up(self) -> bool:
        assert self.proc is not None
        if not self.proc.alive():
            raise ProcessError(f"Orthanc exited at start:\n{self.proc.tail()}")
        try:
            return httpx.get(f"{self.url}/system", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False

    def start(self) -> None:
        """Start it (on the same ports and storage after a stop) and wait for its REST API."""
        self.proc = Proc(f"orthanc:{self.http_port}", [self.executable, str(self.config)], self.workdir / "orthanc.log")
        try:
            wait_until(self._up, 60, "Orthanc's REST API", interval=0.2)
        except TimeoutError as exc:
            raise ProcessError(f"{exc}\n{self.proc.tail()}") from None

    def stop(self) -> None:
        """Stop it (SIGTERM, then SIGKILL)."""
        if self.proc is not None:
            self.proc.stop(grace=10)
            self.proc = None

    def get(self, path: str) -> Any:
        resp = httpx.get(f"{self.url}{path}", timeout=30)
        resp.raise_for_status()
        return resp.json() if "json" in resp.headers.get("content-type", "") else resp.content

    def post(self, path: str, body: Any) -> Any:
        resp = httpx.post(f"{self.url}{path}", json=body, timeout=30)
        resp.raise_for_status()
        return resp.json()

    def instances_of(self, study_uid: str, modality: str) -> list[bytes]:
        """The DICOM files of every instance of ``modality`` in the study."""
        ids = self.post(
            "/tools/find", {"Level": "Instance", "Query": {"StudyInstanceUID": study_uid, "Modality": modality}}
        )
        return [self.get(f"/instances/{i}/file") for i in ids]

    def close(self) -> None:
        self.stop()

    def __enter__(self) -> OrthancServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
