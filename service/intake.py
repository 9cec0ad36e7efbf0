"""Taking an upload in: the job's ``params`` part parsed and validated once (the engine's own parameter dict is
made here and stored; the worker only reads it back), the optional ``callback_url`` checked, the file streamed to
storage and inspected, and the job recorded and enqueued. Nothing of a refused upload is kept."""

from __future__ import annotations

import json
from typing import Any

from fastapi import Request
from pydantic import ValidationError

from core.db import Database, Job
from core.logsafe import escape_control, safe_logger
from core.params import JobParams
from core.settings import Settings
from core.storage import Storage, UploadTooLarge, UploadWriter, is_storage_full, scrub_paths
from core.timings import Timings
from engine.io.predecode import PLANES, ROWS, UploadDecoder
from engine.io.predecode_proc import DecoderProcess
from service.idempotency import Hold, UploadPrint
from service.problems import Problem
from service.services import Services
from service.upload_check import inspect_upload
from service.uploads import UploadError, read_multipart
from service.webhooks import CallbackRefused, check_callback_url

log = safe_logger("bonemesh.api")
PREDECODE_RESERVE = 1 << 30  # disk left free besides the upload and its decoded slices
FULL = "the data volume is full: the upload was not kept; try again later or ask the operator to free space"


async def receive(
    request: Request,
    svc: Services,
    who: str,
    limit: int,
    base_url: str,
    *,
    hold: Hold | None = None,
    fingerprint: UploadPrint | None = None,
) -> Job:
    """Stream, check and record one upload; nothing of a refused one is kept. With an ``Idempotency-Key``, ``hold``
    is kept alive by the body's bytes, and ``fingerprint`` takes the upload's."""
    job_id = Database.new_id()
    timer = Timings(log, "upload timings")  # where the upload's time goes (benchmarks/service.py reads the line)
    writer = await svc.in_upload_thread(svc.storage.upload_writer, job_id, limit)
    decoder = await svc.in_upload_thread(start_decoder, svc, job_id, request.headers.get("content-length"), writer)
    timer.lap("open")

    def write(batch: list[memoryview]) -> None:
        if fingerprint is not None:
            fingerprint.update(batch)
        writer.write_many(batch)
        if isinstance(decoder, DecoderProcess):  # its process reads the file: tell it how far (O(1), never waits)
            writer.flush()
            decoder.advance(writer.size)
        elif decoder is not None:  # the slices decoded as they arrive (never raises)
            decoder.feed(batch)

    try:
        body = request.stream() if hold is None else hold.stream(request.stream())
        parsed = await read_multipart(
            request.headers.get("content-type", ""), body, lambda batch: svc.in_upload_thread(write, batch)
        )
        timer.lap("body")  # received, parsed and written (the last batch's write awaited)
        if fingerprint is not None:
            fingerprint.seal(parsed.filename, parsed.fields)
        if hold is not None:
            hold.working = True
        params, engine = parse_params(parsed.fields.get("params"))
        callback = parsed.fields.get("callback_url", "").strip() or None
        if callback is not None:
            try:
                await svc.in_upload_thread(check_callback_url, callback, svc.settings.webhook_allow_private)
            except CallbackRefused as exc:
                raise Problem(
                    422, str(exc), code="callback_refused", errors=[{"field": "callback_url", "message": str(exc)}]
                ) from None
        timer.lap("fields")
        await svc.in_upload_thread(writer.commit)
        timer.lap("commit")
        if isinstance(decoder, DecoderProcess):  # its last slices and its checks run beside the inspection
            decoder.complete(writer.size)
        summary = await svc.in_upload_thread(_inspect, svc.storage, job_id, parsed.filename, params)
        timer.lap("inspect")
        if decoder is not None:
            await svc.in_upload_thread(finish_decoder, decoder, job_id, writer.size)
            timer.lap("decoder")
        log.info("job %s: upload of %d bytes: %s", job_id, writer.size, summary)
        name = parsed.filename or "upload"
        if hold is not None:  # the key is still this request's: nobody made the job meanwhile
            await svc.in_upload_thread(hold.still_held)
        job: Job = await svc.in_upload_thread(
            svc.accept, job_id, who, params.record(), engine, name, writer.size, callback, base_url
        )
        timer.lap("record")
        timer.log(job_id)
        return job
    except Exception as exc:
        if decoder is not None:
            await svc.in_upload_thread(decoder.abort)
        await svc.in_upload_thread(svc.discard, writer, job_id)
        if isinstance(exc, UploadTooLarge):
            raise Problem(413, str(exc)) from None
        if isinstance(exc, UploadError):
            raise Problem(exc.status, exc.detail) from None
        if is_storage_full(exc):
            log.error("job %s: upload refused, the data volume is full (%s)", job_id, exc)
            raise Problem(507, FULL) from None
        raise
    except BaseException:  # cancelled: clean up without awaiting
        if decoder is not None:
            decoder.abort()
        svc.discard(writer, job_id)
        raise


def start_decoder(
    svc: Services, job_id: str, content_length: str | None, writer: UploadWriter | None = None
) -> UploadDecoder | DecoderProcess | None:
    """A decoder of the upload's PNG slices as they arrive (``engine.io.predecode``), where the settings ask for
    one, the request's length is unknown or at least ``BONEMESH_PREDECODE_MIN_BYTES``, the store is local disk, and
    its disk has room for the decoded volume (about three times the upload, judged from that length); else None. In
    a child process reading ``writer``'s file as it grows (``engine.io.predecode_proc``) where
    ``BONEMESH_PREDECODE_PROCESS`` (the default), else on threads here."""
    path = svc.storage.predecode_path(job_id)
    if not svc.settings.decode_during_upload or path is None:
        return None
    try:
        size = int(content_length or 0)
        if content_length is not None and size < svc.settings.predecode_min_bytes:
            return None  # the worker decodes a small scan's few slices faster than a child is started and fed
        free = svc.storage.free_bytes()
        if free is not None and free < PREDECODE_RESERVE + 3 * size:
            return None
        from engine.io.parallel import decode_threads

        threads = decode_threads(svc.settings.predecode_threads)
        layout = predecode_layout(svc.settings)
        part = writer.local_part() if writer is not None else None
        if svc.settings.predecode_process and svc.decoders is not None and part is not None:
            return svc.decoders.start(path, part, threads, layout)
        return UploadDecoder(path, threads=threads, layout=layout)
    except Exception as exc:  # never a reason to refuse the upload
        log.warning("job %s: no decoding during the upload (%s)", job_id, type(exc).__name__)
        return None


def predecode_layout(settings: Settings) -> str:
    """What the upload's decoder writes (``engine.io.predecode``): a PNG's filtered rows, only inflated (about a third
    of a slice's decoding), where the workers may unfilter them on a GPU (``BONEMESH_DEVICE`` other than ``cpu``,
    ``BONEMESH_PNG_DECODER`` ``auto``; a worker without one unfilters them on its host); else the samples."""
    return ROWS if settings.device != "cpu" and settings.png_decoder == "auto" else PLANES


def finish_decoder(decoder: UploadDecoder | DecoderProcess, job_id: str, size: int) -> None:
    """Keep the decoded slices where they are the stack the worker would decode, else drop them (logged); the
    upload is complete and committed (``size`` bytes)."""
    if isinstance(decoder, DecoderProcess):
        kept = decoder.finish(size)
        slices, where = (
            decoder.slices,
            " (in a process: " + ", ".join(f"{k} {v:.3f}" for k, v in decoder.timings.items()) + ")",
        )
    else:
        kept = decoder.finish()
        slices, where = sum(m["png"] for m in decoder.members), ""
    if kept:
        log.info("job %s: %d slice(s) decoded during the upload%s", job_id, slices, where)
    elif decoder.reason:
        log.info("job %s: slices not decoded during the upload: %s", job_id, escape_control(decoder.reason))


async def fingerprint_of(request: Request, svc: Services, limit: int) -> str:
    """The fingerprint of an upload sent again with its ``Idempotency-Key`` (read and hashed, never kept).

    Raises:
        Problem: as :func:`receive` for a malformed body; 413 past ``limit``.
    """
    print_ = UploadPrint()
    seen = 0

    def digest(batch: list[memoryview]) -> None:
        nonlocal seen
        seen += sum(len(b) for b in batch)
        if seen > limit:
            raise UploadTooLarge(f"the upload is over the limit of {limit:,} bytes")
        print_.update(batch)

    try:
        parsed = await read_multipart(
            request.headers.get("content-type", ""),
            request.stream(),
            lambda batch: svc.in_upload_thread(digest, batch),
        )
    except UploadTooLarge as exc:
        raise Problem(413, str(exc)) from None
    except UploadError as exc:
        raise Problem(exc.status, exc.detail) from None
    print_.seal(parsed.filename, parsed.fields)
    return print_.hexdigest()


def _inspect(storage: Storage, job_id: str, filename: str | None, params: JobParams) -> str:
    """``inspect_upload`` on the committed upload (a scratch copy where the store is not local disk)."""
    with storage.inspect_path(job_id) as path:
        try:
            return inspect_upload(path, filename, params)
        except UploadError as exc:  # never a server path in the answer
            shown = escape_control(filename) if filename else "the upload"
            exc.detail = scrub_paths(exc.detail, {**storage.local_paths(job_id), str(path): shown})
            raise


def parse_params(text: str | None) -> tuple[JobParams, dict[str, Any]]:
    """The client's parameters and the engine's record of them (``engine.job.JobSpec.to_dict``: ``recon``,
    ``spacing_zyx_mm``, ``input``, ``outputs``), validated once.

    Raises:
        Problem: 422 naming the field when a value is refused (by the schema or by the engine).
    """
    if text is None or not text.strip():
        params = JobParams()
    else:
        params = _validate(text)
    try:
        engine = params.engine_params()
    except ValueError as exc:
        raise Problem(422, f"params: {exc}", errors=[{"field": "params", "message": str(exc)}]) from None
    return params, engine


def _validate(text: str) -> JobParams:
    try:
        data = json.loads(text)
    except (ValueError, RecursionError) as exc:
        reason = "it is nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise Problem(422, f"params is not valid JSON: {reason}") from None
    if not isinstance(data, dict):
        raise Problem(422, "params must be a JSON object")
    try:
        return JobParams.model_validate(data)
    except (ValidationError, RecursionError) as exc:
        if isinstance(exc, RecursionError):
            raise Problem(422, "params is nested too deeply") from None
        errs = [
            {"field": ".".join(["params", *(str(p) for p in e["loc"])]).rstrip("."), "message": e["msg"]}
            for e in exc.errors()
        ]
        raise Problem(422, "; ".join(f"{e['field']}: {e['message']}" for e in errs), errors=errs) from None
