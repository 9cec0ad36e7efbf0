"""Clients of the configured DICOMweb servers: credentials come from the settings only.

Fetching a series is complete or fails. The server's QIDO-RS list of the series' instances (every page) is what
must arrive. WADO-RS retrieves the series asking for any transfer syntax (``transfer-syntax=*``), else for the
lossless ones the loader decodes here (:func:`decodable_syntaxes`), else for the server's default; a part of the
multipart answer is kept only when the answer's framing shows it whole (a following boundary, its Content-Length).
What the series answer lacks (cut short, as Orthanc does when it cannot transcode an instance to the syntax asked
for, while still answering 200) is retrieved instance by instance, as is an instance sent in a syntax not decodable
here. Transient errors (no connection, a time-out, HTTP 429 or 5xx, a body cut short) are retried with exponential
backoff and jitter (``DicomwebServer.attempts`` and ``backoff_seconds``: :func:`retry_delay`), never sooner than the
server's ``Retry-After`` asks (seconds or an HTTP date, honoured up to :data:`MAX_RETRY_AFTER`). When an instance
the server lists is still missing, :class:`SeriesIncomplete` carries the counts; the caller discards the folder.

The WADO-RS and QIDO-RS requests are made here with the settings' session, not with dicomweb-client's
``iter_series``: its multipart decoder yields an unterminated last part as if it were whole, and it refuses more
than one transfer syntax in an Accept. Error messages name the transaction and the cause, never a URL.
"""

from __future__ import annotations

import datetime as dt
import io
import random
import time
import warnings
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from email.utils import parsedate_to_datetime
from pathlib import Path
from typing import Any, TypeVar

from core.pacs.config import DicomwebServer
from core.pacs.multipart import MultipartError, response_parts

EXTRA = "bonemesh[pacs]"
QIDO_PAGE = 500  # instances asked for per QIDO-RS request (a server may answer fewer: the next page is asked for)
MAX_PAGES = 10_000
GIVE_UP_AFTER = 3  # instances that could not be retrieved at all: the series cannot be complete, stop trying
REFUSED = frozenset({400, 406, 415})  # the server does not serve this Accept: the next one is tried
DENIED = frozenset({401, 403})
GONE = frozenset({404, 410})
_DICOM = 'multipart/related; type="application/dicom"'
MAX_RETRY_AFTER = 120.0  # the longest Retry-After honoured (a server asking more is asked again after this)
T = TypeVar("T")


class DicomwebError(Exception):
    """A DICOMweb request failed; the message names what failed and why, never a URL.

    Attributes:
        transient: worth retrying (no connection, a time-out, HTTP 429 or 5xx, a body cut short).
        status: the HTTP status, when the server answered with an error.
        retry_after: the seconds the server's ``Retry-After`` asked to wait, when it sent one.
    """

    def __init__(
        self, message: str, *, transient: bool = False, status: int | None = None, retry_after: float | None = None
    ) -> None:
        super().__init__(message)
        self.transient, self.status, self.retry_after = transient, status, retry_after


def parse_retry_after(value: str | None, now: dt.datetime | None = None) -> float | None:
    """The seconds a ``Retry-After`` header asks for (delta-seconds or an HTTP date; RFC 9110), at most
    :data:`MAX_RETRY_AFTER`; None when absent or unreadable."""
    if value is None or not value.strip():
        return None
    text = value.strip()
    if text.isdigit():
        return min(float(text), MAX_RETRY_AFTER)
    try:
        when = parsedate_to_datetime(text)
    except (TypeError, ValueError, IndexError):
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=dt.UTC)
    seconds = (when - (now or dt.datetime.now(dt.UTC))).total_seconds()
    return min(max(seconds, 0.0), MAX_RETRY_AFTER)


def retry_delay(server: DicomwebServer, attempt: int, error: DicomwebError | None = None) -> float:
    """The wait before try ``attempt + 1``: exponential backoff (``backoff_seconds`` doubling) with equal jitter
    (between half and all of it, so clients that failed together do not come back together), and never less than
    the server's ``Retry-After`` (plus a little jitter of its own)."""
    base = server.backoff_seconds * 2 ** (attempt - 1)
    delay = base / 2 + random.uniform(0, base / 2)  # jitter, not a secret
    if error is not None and error.retry_after is not None:
        delay = max(delay, error.retry_after + random.uniform(0, min(1.0, base / 2)))
    return float(delay)


@dataclass(frozen=True)
class FetchResult:
    """What a series fetch found: the counts, the instances still missing, the transfer syntaxes kept."""

    expected: int  # instances the server lists (QIDO-RS)
    retrieved: int  # of those, retrieved whole
    missing: tuple[str, ...]  # SOP Instance UIDs listed but not retrieved
    transfer_syntaxes: dict[str, int] = field(default_factory=dict)  # UID -> files kept
    one_by_one: int = 0  # instances retrieved one by one (the series answer lacked them, or not decodable here)
    duplicates: int = 0  # parts that repeated an instance already kept
    unlisted: int = 0  # instances of the series retrieved although the list lacked them (kept)


class SeriesIncomplete(Exception):
    """Instances the server lists are missing after every retry; ``result`` has the counts and the UIDs."""

    def __init__(self, result: FetchResult) -> None:
        super().__init__(f"{result.retrieved} of {result.expected} instances retrieved ({len(result.missing)} missing)")
        self.result = result


def session_for(server: DicomwebServer) -> Any:
    """A ``requests.Session`` with the server's credentials (HTTP basic auth or a bearer token)."""
    import requests

    session = requests.Session()
    if server.username is not None:
        session.auth = (server.username, server.password.get_secret_value() if server.password else "")
    if server.token is not None:
        session.headers["Authorization"] = f"Bearer {server.token.get_secret_value()}"
    return session


def client_for(server: DicomwebServer) -> Any:
    """A ``dicomweb_client.DICOMwebClient`` for a configured server (credentials from the settings).

    Raises:
        ImportError: dicomweb-client is not installed (the message names the extra).
    """
    try:
        from dicomweb_client.api import DICOMwebClient
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ImportError(f"DICOMweb needs dicomweb-client: pip install '{EXTRA}'") from exc
    return DICOMwebClient(url=server.url.rstrip("/"), session=session_for(server), timeout=server.timeout_seconds)


def decodable_syntaxes() -> tuple[str, ...]:
    """The lossless transfer syntaxes whose pixels pydicom decodes here (with the installed pylibjpeg plugins).

    Only lossless ones: asked for a list, a server may transcode, and a lossy transcode would change the bone's
    surface. (Asked for ``*``, a server sends what it stores, lossy or not: the scanner's own data.)
    """
    import pydicom.uid as u
    from pydicom.pixels import get_decoder

    compressed = (u.RLELossless, u.JPEG2000Lossless, u.HTJ2KLossless, u.HTJ2KLosslessRPCL, u.JPEGLSLossless)
    compressed += (u.JPEGLosslessSV1, u.JPEGLossless)
    kept = [ts for ts in compressed if get_decoder(ts).is_available]
    return (u.ExplicitVRLittleEndian, u.DeflatedExplicitVRLittleEndian, *kept)


def accepts(*, one_by_one: bool = False) -> list[tuple[str, str]]:
    """The Accept headers of WADO-RS retrieval, in the order tried: (name, header value). ``one_by_one`` adds each
    decodable syntax alone before the server's default: some servers read only one syntax of a list (Orthanc: the
    last), and cannot transcode an instance into it, but send it as stored when that syntax alone is asked for."""
    syntaxes = decodable_syntaxes()
    listed = ", ".join(f"{_DICOM}; transfer-syntax={ts}" for ts in syntaxes)
    alone = [(ts, f"{_DICOM}; transfer-syntax={ts}") for ts in syntaxes] if one_by_one else []
    return [("any", f"{_DICOM}; transfer-syntax=*"), ("decodable", listed), *alone, ("default", _DICOM)]


def fetch_series(
    server: DicomwebServer, study_uid: str, series_uid: str, folder: Path, *, page: int = QIDO_PAGE
) -> FetchResult:
    """Retrieve every instance of a series into ``folder`` (one Part 10 file each, in the syntax sent).

    Raises:
        DicomwebError: the server could not be reached, refused, or lists no instance of the series.
        SeriesIncomplete: an instance it lists is still missing after every retry.
    """
    session = session_for(server)
    base = f"{server.url.rstrip('/')}/studies/{study_uid}/series/{series_uid}"
    try:
        listed = list_instances(_Qido(session, server, base), page)
        if not listed:
            raise DicomwebError("the server lists no instance of the series (QIDO-RS)")
        folder.mkdir(parents=True, exist_ok=True)
        store = _Store(folder, series_uid)
        refused = _series_pass(session, server, base, store, accepts())
        todo = [uid for uid in listed if uid not in store.files]
        todo += [uid for uid in store.undecodable if uid not in todo]
        variants = [v for v in accepts(one_by_one=True) if v[0] not in refused]
        _instance_pass(session, server, base, store, todo, variants)
    finally:
        session.close()
    missing = tuple(uid for uid in listed if uid not in store.files)
    result = FetchResult(
        expected=len(listed),
        retrieved=len(listed) - len(missing),
        missing=missing,
        transfer_syntaxes=dict(Counter(store.syntax.values())),
        one_by_one=store.one_by_one,
        duplicates=store.duplicates,
        unlisted=len(store.files.keys() - set(listed)),
    )
    if missing:
        raise SeriesIncomplete(result)
    return result


def list_instances(get_page: Callable[[dict[str, int]], list[Any]], page: int = QIDO_PAGE) -> list[str]:
    """SOP Instance UIDs of every page of a QIDO-RS search, in order, each once.

    ``get_page({"limit": n, "offset": k})`` answers one page. Pages are asked for until one is empty or brings no
    new instance (a server that ignores ``offset``); a server may answer fewer than ``limit`` (its own cap).
    """
    seen: dict[str, None] = {}
    offset = 0
    for _ in range(MAX_PAGES):
        batch = get_page({"limit": page, "offset": offset})
        before = len(seen)
        for item in batch:
            try:
                seen.setdefault(str(item["00080018"]["Value"][0]), None)
            except (KeyError, IndexError, TypeError):
                raise DicomwebError("the QIDO-RS answer lacks the instances' SOP Instance UIDs") from None
        if not batch or len(seen) == before:
            return list(seen)
        offset += len(batch)
    raise DicomwebError(f"the QIDO-RS search did not end after {MAX_PAGES} pages")


class _Qido:
    """One page of the QIDO-RS search of a series' instances (retried); for :func:`list_instances`."""

    WHAT = "QIDO-RS search of the series' instances"

    def __init__(self, session: Any, server: DicomwebServer, base: str) -> None:
        self.session, self.server, self.url = session, server, f"{base}/instances"
        self.unpaged = False  # the server refused limit/offset: its first answer was the whole list

    def __call__(self, params: dict[str, int]) -> list[Any]:
        if self.unpaged:
            return []
        try:
            return _retrying(self.server, lambda: self._page(params), self.WHAT)
        except DicomwebError as exc:
            if exc.status != 400 or params.get("offset"):
                raise
            self.unpaged = True
            return _retrying(self.server, lambda: self._page(None), self.WHAT)

    def _page(self, params: dict[str, int] | None) -> list[Any]:
        import requests

        resp = _get(self.session, self.server, self.url, "application/dicom+json", params)
        try:
            if resp.status_code == 204 or not resp.content:
                return []
            body = resp.json()
        except ValueError:
            raise DicomwebError("the QIDO-RS answer is not JSON", transient=True) from None
        except requests.RequestException as exc:
            raise DicomwebError(f"the answer was cut short ({type(exc).__name__})", transient=True) from None
        finally:
            resp.close()
        if isinstance(body, dict):  # one data set instead of an array
            body = [body]
        if not isinstance(body, list):
            raise DicomwebError("the QIDO-RS answer is not a list of instances")
        return body


def _get(session: Any, server: DicomwebServer, url: str, accept: str, params: Any = None) -> Any:
    """GET; DicomwebError (transient or not) for no answer or an error status."""
    import requests

    try:
        resp = session.get(url, headers={"Accept": accept}, params=params, timeout=server.timeout_seconds, stream=True)
    except requests.Timeout:
        raise DicomwebError(f"no answer within {server.timeout_seconds:g} s", transient=True) from None
    except requests.RequestException as exc:
        raise DicomwebError(f"no connection ({type(exc).__name__})", transient=True) from None
    if resp.status_code >= 400:
        resp.close()
        code = resp.status_code
        wait = parse_retry_after(resp.headers.get("Retry-After"))
        raise DicomwebError(f"HTTP {code}", transient=code == 429 or code >= 500, status=code, retry_after=wait)
    return resp


def _retrying(server: DicomwebServer, call: Callable[[], T], what: str) -> T:
    """``call()``, retried on a transient DicomwebError with exponential backoff; the last error names ``what``."""
    attempt = 1
    while True:
        try:
            return call()
        except DicomwebError as exc:
            if not exc.transient or attempt >= server.attempts:
                tries = f" after {attempt} attempts" if attempt > 1 else ""
                raise DicomwebError(f"{what}: {exc}{tries}", transient=exc.transient, status=exc.status) from None
            last = exc
        time.sleep(retry_delay(server, attempt, last))
        attempt += 1


def _retrieve(session: Any, server: DicomwebServer, url: str, accept: str) -> Iterator[bytes]:
    """The whole instances of a WADO-RS answer; DicomwebError (transient, with the answer's status) after them if
    the answer was cut short."""
    resp = _get(session, server, url, accept)
    try:
        yield from response_parts(resp)
    except MultipartError as exc:
        raise DicomwebError(str(exc), transient=exc.cut, status=resp.status_code) from None


class _Store:
    """The instances kept in ``folder``: one file per SOP Instance UID, in the transfer syntax sent."""

    def __init__(self, folder: Path, series_uid: str) -> None:
        from pydicom.uid import ExplicitVRBigEndian, ImplicitVRLittleEndian

        self.folder, self.series_uid = folder, series_uid
        self.decodable = {*decodable_syntaxes(), ImplicitVRLittleEndian, ExplicitVRBigEndian}
        self.files: dict[str, Path] = {}
        self.syntax: dict[str, str] = {}
        self.undecodable: list[str] = []  # images kept in a syntax not decodable here (asked for again one by one)
        self.duplicates = self.one_by_one = 0

    def add(self, data: bytes, *, again: bool = False) -> None:
        """Keep one retrieved instance of the series (``again``: one asked for by itself)."""
        ds, data = _part10(data)
        uid, syntax = str(ds.SOPInstanceUID), str(ds.file_meta.TransferSyntaxUID)
        if ds.get("SeriesInstanceUID") != self.series_uid:
            return
        if uid in self.files and (uid not in self.undecodable or not again):
            self.duplicates += 0 if again else 1
            return
        path = self.files.get(uid) or self.folder / f"{len(self.files) + 1:06d}.dcm"
        path.write_bytes(data)
        self.files[uid], self.syntax[uid] = path, syntax
        if uid in self.undecodable:
            self.undecodable.remove(uid)
        if "Rows" in ds and syntax not in self.decodable:
            self.undecodable.append(uid)
        self.one_by_one += int(again)


def _part10(data: bytes) -> tuple[Any, bytes]:
    """The header of a retrieved instance and its bytes as a Part 10 file (a bare data set given its file meta)."""
    import pydicom
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(io.BytesIO(data), force=True, stop_before_pixels=True)
            str(ds.SOPInstanceUID)
            if "TransferSyntaxUID" in ds.file_meta:
                return ds, data
            ds = pydicom.dcmread(io.BytesIO(data), force=True)
            meta = FileMetaDataset()
            meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = ds.SOPClassUID, ds.SOPInstanceUID
            meta.TransferSyntaxUID = ImplicitVRLittleEndian if ds.original_encoding[0] else ExplicitVRLittleEndian
            ds.file_meta = meta
            buf = io.BytesIO()
            ds.save_as(buf, enforce_file_format=True)
            return ds, buf.getvalue()
    except Exception:
        raise DicomwebError("a part of the WADO-RS answer is not a readable DICOM instance") from None


def _series_pass(session: Any, server: DicomwebServer, base: str, store: _Store, variants: list[Any]) -> set[str]:
    """Retrieve the series in one answer, with the first Accept the server serves; the names of those it refused.

    Returns after the first answer that brought instances, whole or cut short (the rest comes one by one).

    Raises:
        DicomwebError: the server cannot be reached, or refuses the credentials.
    """
    refused: set[str] = set()
    for name, accept in variants:
        attempt = 1
        while True:
            before = len(store.files) + store.duplicates
            try:
                for part in _retrieve(session, server, base, accept):
                    store.add(part)
                return refused
            except DicomwebError as exc:
                if len(store.files) + store.duplicates > before:
                    return refused
                if exc.status in DENIED or (exc.transient and exc.status is None and attempt >= server.attempts):
                    raise DicomwebError(f"WADO-RS retrieval of the series: {exc}", status=exc.status) from None
                if exc.status in REFUSED:
                    refused.add(name)
                if not exc.transient or attempt >= server.attempts:
                    break
                last = exc
            time.sleep(retry_delay(server, attempt, last))
            attempt += 1
    return refused


def _instance_pass(
    session: Any, server: DicomwebServer, base: str, store: _Store, todo: list[str], variants: list[Any]
) -> None:
    """Retrieve each of ``todo`` by itself, each Accept in turn, in up to ``server.attempts`` rounds with exponential
    backoff between them; an instance the server does not have (404, 410) is not asked for again. Once
    ``GIVE_UP_AFTER`` instances could not be had, the series cannot be complete: the rest get one round each (the
    counts stay exact), or none when the server no longer answers.

    Raises:
        DicomwebError: the server refuses the credentials.
    """
    failed = 0
    for uid in todo:
        url, redo = f"{base}/instances/{uid}", uid in store.files  # redo: kept in a syntax not decodable here
        down = gone = False
        last: DicomwebError | None = None  # the last error of the round before (its Retry-After is honoured)
        for attempt in range(1 if failed >= GIVE_UP_AFTER else server.attempts):
            if attempt:
                time.sleep(retry_delay(server, attempt, last))
            for name, accept in variants:
                if redo and name == "any":
                    continue
                try:
                    for part in _retrieve(session, server, url, accept):
                        store.add(part, again=True)
                except DicomwebError as exc:
                    if exc.status in DENIED:
                        raise DicomwebError(f"WADO-RS retrieval of an instance: {exc}", status=exc.status) from None
                    down, gone, last = exc.transient and exc.status is None, exc.status in GONE, exc
                    if down or gone:
                        break
                    continue
                if uid in store.files and uid not in store.undecodable:
                    break
            if gone or (uid in store.files and uid not in store.undecodable):
                break
        if uid not in store.files:
            failed += 1
            if down and failed >= GIVE_UP_AFTER:
                return


def store_datasets(server: DicomwebServer, datasets: Sequence[Any]) -> None:
    """Store DICOM data sets with one STOW-RS request (a label job's models: one instance per label).

    Raises:
        requests.HTTPError, requests.ConnectionError: the server refused or could not be reached.
        RuntimeError: the server answered but lists an instance as failed.
    """
    response = client_for(server).store_instances(datasets)
    failed = response.get("FailedSOPSequence") if response is not None else None
    if failed:
        reason = failed[0].get("FailureReason", "?")
        raise RuntimeError(
            f"STOW-RS: the server refused {len(failed)} of {len(datasets)} instance(s) (failure reason {reason})"
        )
