"""The storage SCP (pynetdicom): accepts CT and Enhanced CT images, and segmentations (SEG) of them, from
allow-listed calling AEs and puts them in the inbox.

Associations are checked at request time (``EVT_REQUESTED``): a calling AE title (and address, where the entry
names one) that is not on the allow-list gets an A-ASSOCIATE-RJ, rejected-permanent, "calling AE title not
recognised". Presentation contexts are offered only for the storage SOP classes below with the listed transfer
syntaxes; anything else is refused in negotiation, and a C-STORE that still carries another SOP class gets
0x0122 (SOP class not supported). The log names AE titles, addresses and UIDs, never patient data.
"""

from __future__ import annotations

import logging
from typing import Any

from core.logsafe import safe_logger
from core.pacs.config import PacsSettings
from service.pacs.inbox import Inbox

log = safe_logger("bonemesh.pacs")

CT_IMAGE = "1.2.840.10008.5.1.4.1.1.2"
ENHANCED_CT_IMAGE = "1.2.840.10008.5.1.4.1.1.2.1"
LEGACY_ENHANCED_CT_IMAGE = "1.2.840.10008.5.1.4.1.1.2.2"
SEGMENTATION = "1.2.840.10008.5.1.4.1.1.66.4"
LABEL_MAP_SEGMENTATION = "1.2.840.10008.5.1.4.1.1.66.7"
# CT images become bone models; a segmentation of a CT becomes a model per segment (``core.pacs.routing``)
STORAGE_CLASSES = (CT_IMAGE, ENHANCED_CT_IMAGE, LEGACY_ENHANCED_CT_IMAGE, SEGMENTATION, LABEL_MAP_SEGMENTATION)
TRANSFER_SYNTAXES = (
    "1.2.840.10008.1.2.1",  # Explicit VR Little Endian
    "1.2.840.10008.1.2",  # Implicit VR Little Endian
    "1.2.840.10008.1.2.1.99",  # Deflated Explicit VR Little Endian
    "1.2.840.10008.1.2.4.70",  # JPEG Lossless, first-order prediction (SV1)
    "1.2.840.10008.1.2.4.57",  # JPEG Lossless
    "1.2.840.10008.1.2.4.90",  # JPEG 2000 lossless
    "1.2.840.10008.1.2.4.91",  # JPEG 2000
    "1.2.840.10008.1.2.4.80",  # JPEG-LS lossless
    "1.2.840.10008.1.2.5",  # RLE Lossless
)
VERIFICATION = "1.2.840.10008.1.1"

SUCCESS = 0x0000
SOP_CLASS_NOT_SUPPORTED = 0x0122
OUT_OF_RESOURCES = 0xA700
DATASET_MISMATCH = 0xA900
CANNOT_UNDERSTAND = 0xC000


class StorageSCP:
    """A storage SCP feeding ``inbox``; ``start()`` listens in background threads, ``stop()`` closes.

    Args:
        pacs: the settings (AE title, address, port, allow-list).
        inbox: where instances go.
    """

    def __init__(self, pacs: PacsSettings, inbox: Inbox) -> None:
        self.pacs = pacs
        self.inbox = inbox
        self.server: Any = None
        self.stored = 0

    def application_entity(self) -> Any:
        """The pynetdicom AE with the supported presentation contexts."""
        from pynetdicom import AE

        ae = AE(ae_title=self.pacs.ae_title)
        for sop_class in STORAGE_CLASSES:
            ae.add_supported_context(sop_class, list(TRANSFER_SYNTAXES))
        ae.add_supported_context(VERIFICATION)
        ae.maximum_associations = 16
        ae.network_timeout = ae.acse_timeout = ae.dimse_timeout = 60
        return ae

    def start(self) -> None:
        """Listen on the configured address and port (returns at once)."""
        from pynetdicom import evt

        logging.getLogger("pynetdicom").setLevel(logging.WARNING)  # its debug dumps would show datasets
        handlers = [(evt.EVT_REQUESTED, self._on_requested), (evt.EVT_C_STORE, self._on_store)]
        self.server = self.application_entity().start_server(
            (self.pacs.host, self.pacs.port), block=False, evt_handlers=handlers
        )
        log.info("storage SCP %s listening on %s:%d", self.pacs.ae_title, self.pacs.host, self.port)

    @property
    def port(self) -> int:
        """The port listened on (the configured one, or the one the system chose for port 0)."""
        return int(self.server.server_address[1]) if self.server is not None else self.pacs.port

    def stop(self) -> None:
        if self.server is not None:
            self.server.shutdown()
            self.server = None

    def _on_requested(self, event: Any) -> None:
        assoc = event.assoc
        calling = str(assoc.requestor.primitive.calling_ae_title).strip()
        address = str(assoc.requestor.address)
        if self.pacs.admits(calling, address):
            return
        log.warning("association from %s rejected: calling AE %r is not on the allow-list", address, calling)
        assoc.acse.send_reject(0x01, 0x01, 0x03)  # rejected-permanent, service user, calling AE not recognised
        assoc.is_rejected = True
        assoc.kill()

    def _on_store(self, event: Any) -> int:
        from pydicom.filewriter import write_file_meta_info

        sop_class = str(event.context.abstract_syntax)
        if sop_class not in STORAGE_CLASSES:
            return SOP_CLASS_NOT_SUPPORTED
        try:
            ds = event.dataset
            study, series, sop = (
                str(ds.get(k, "")) for k in ("StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID")
            )
            declared = str(ds.get("SOPClassUID", ""))
        except Exception as exc:
            log.warning(
                "C-STORE from %s: undecodable data set (%s)", event.assoc.requestor.ae_title, type(exc).__name__
            )
            return CANNOT_UNDERSTAND
        if declared != sop_class:
            return DATASET_MISMATCH
        sender = {
            "ae_title": str(event.assoc.requestor.ae_title).strip(),
            "address": str(event.assoc.requestor.address),
        }
        raw = event.request.DataSet.getvalue()

        def write(fh: Any) -> None:
            fh.write(b"\x00" * 128 + b"DICM")
            write_file_meta_info(fh, event.file_meta, enforce_standard=True)
            fh.write(raw)

        try:
            self.inbox.store(study, series, sop, sender, write)
        except ValueError:
            log.warning("C-STORE from %s: malformed Study/Series/SOP Instance UID; refused", sender["ae_title"])
            return CANNOT_UNDERSTAND
        except OSError as exc:
            log.error("C-STORE of %s: could not write it (%s)", sop, exc.strerror or type(exc).__name__)
            return OUT_OF_RESOURCES
        self.stored += 1
        return SUCCESS
