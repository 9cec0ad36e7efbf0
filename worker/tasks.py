"""The reconstruction task: claim the job, load the upload, run ``engine.reconstruct``, stage the outputs and
publish them in one rename, then record success. Idempotent per job id: a duplicate or redelivered message finds
the job claimed or finished and does nothing; a rerun after a killed worker rebuilds the outputs from the upload.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import functools
import os
import random
import socket
import threading
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Any

from celery.exceptions import SoftTimeLimitExceeded

from core.db import Database, utcnow
from core.faults import Outage, outage_of, retrying
from core.logsafe import escape_control, relabel, safe_logger
from core.settings import Settings, get_settings
from core.storage import is_storage_full, scrub_exception, scrub_paths, storage_from_settings, version_of
from core.timings import Timings
from engine.io.predecode import remove_predecoded
from engine.job import FILES, LABELS_ZIP, triangle_count
from worker.app import app, runtime_of
from worker.pacs import (
    SourceIncomplete,
    SourceUnavailable,
    UncheckedSource,
    fetch_source,
    write_dicom_labels,
    write_dicom_model,
)

if TYPE_CHECKING:
    from engine.job import JobSpec

log = safe_logger("bonemesh.worker")  # job ids and engine messages only: never the upload's name
# job progress (a fraction; the holder records percent) at each point: loading 0-5 %, pipeline 5-90 %, the files
LOAD_END, PIPELINE_END = 0.05, 0.9


class Cancelled(Exception):
    """The job was cancelled (or taken over) while it ran."""


class _Holder:
    """The claim of one run: heartbeats and progress written by a thread, cancellation noticed.

    ``progress`` never waits for the database: it leaves the newest (stage, percent) for the thread, which writes it
    at once (coalescing what came meanwhile) and beats every ``every`` seconds otherwise. The pipeline reports each
    decimation pass; written in line, each commit held the GPU work behind the database's disk (on the 2 x H200
    host, with uploads being written, decimation took 0.8 s instead of 0.27 s).
    """

    def __init__(self, db: Database, job_id: str, worker: str, every: float) -> None:
        self.db, self.job_id, self.worker, self.every = db, job_id, worker, every
        self.lost = threading.Event()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._pending: tuple[str, float] | None = None
        self._thread = threading.Thread(target=self._run, name=f"heartbeat-{job_id[:8]}", daemon=True)

    def __enter__(self) -> _Holder:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(self.every)
            self._wake.clear()
            if self._stop.is_set():
                return
            pending, self._pending = self._pending, None
            values: dict[str, Any] = {} if pending is None else {"stage": pending[0], "progress": pending[1]}
            try:
                if not self.db.beat(self.job_id, self.worker, **values):
                    self.lost.set()
            except Exception as exc:  # the database busy for a moment
                log.warning("heartbeat of %s: %s", self.job_id, exc)

    def progress(self, stage: str, percent: float) -> None:
        """Record the job's stage and percent (written by the thread); raises Cancelled once the claim is lost."""
        if self.lost.is_set():
            raise Cancelled(self.job_id)
        self._pending = (stage, percent)
        self._wake.set()


@functools.cache
def database(url: str) -> Database:
    """One :class:`Database` (one connection pool, schema checked once) per URL for the worker process."""
    return Database(url)


@app.task(name="bonemesh.reconstruct", bind=True)
def reconstruct_job(self: Any, job_id: str) -> str:
    """Run one job (see the module docstring); returns what happened, for the worker's log."""
    settings = get_settings()
    db = database(settings.db_url)
    storage = storage_from_settings(settings)
    host = socket.gethostname()
    worker = f"{host}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
    stale_before = utcnow() - dt.timedelta(seconds=settings.stale_seconds)
    name = getattr(self.request, "hostname", None) or worker  # the Celery node name: the job shows who ran it
    timer = Timings(log)
    job = db.claim(job_id, worker, stale_before, name=name, host=host)
    timer.lap("claim")
    if job is None:
        log.info("job %s: already taken, finished or cancelled; message dropped", job_id)
        return "skipped"
    lost = job.attempts - db.outages(job_id)  # attempts given back for an outage are not the worker's doing
    if lost > settings.max_attempts:
        db.finish(
            job_id,
            worker,
            "failed",
            error_code="worker_lost",
            error_message=f"the job stopped its worker {lost - 1} times (out of memory or a crash); "
            "try a smaller scan or crop it",
        )
        return "failed"
    staged: Path | None = None
    labels = storage.local_paths(job_id)  # server paths a message may carry, and the words shown instead
    try:
        with _Holder(db, job_id, worker, settings.heartbeat_seconds) as holder:
            left = storage.clean_staging(job_id)  # a killed earlier attempt's staging folders
            if left:
                log.info("job %s: removed %d folder(s) left by an earlier attempt", job_id, left)
            staged = storage.staging_dir(job_id)
            labels[str(staged)] = "the job's outputs"
            timer.lap("staging")
            with storage.local_upload(job_id) as upload:  # a scratch copy where the store is not local
                timer.lap("upload_copy")
                labels[str(upload)] = "upload"
                outputs = _run(job, upload, staged, holder, settings, db, timer)
            timer.lap("release")
            if holder.lost.is_set():
                raise Cancelled(job_id)
            within = settings.outage_seconds  # the store or the database down for a moment: tried again (core.faults)
            ready = staged
            version = retrying(lambda: storage.publish(job_id, ready), within=within, doing="publishing the models")
            timer.lap("publish")  # invisible until the commit below records it
            staged = None
            outputs = [{**o, "version": version} for o in outputs]
            done = retrying(
                lambda: db.finish(job_id, worker, "succeeded", outputs=outputs, stage="done", progress=100.0),
                within=within,
                doing="recording the job's success",
            )
            if not done:
                raise Cancelled(job_id)
            timer.lap("finish")
            with contextlib.suppress(Exception):  # older versions: removed now, or by the next attempt or deletion
                storage.retire(job_id, keep=version)
            timer.lap("retire")
        return "succeeded"
    except Cancelled:
        log.info("job %s: cancelled, deleted or taken over while running; its files are dropped", job_id)
        current = db.get(job_id)
        if current is None or current.state == "cancelled":
            storage.delete_job(job_id)
        return "cancelled"
    except SoftTimeLimitExceeded:
        db.finish(
            job_id,
            worker,
            "failed",
            error_code="time_limit",
            error_message=f"the reconstruction took longer than {settings.job_soft_time_limit} s and was stopped; "
            "try a larger reduction, a crop, or a GPU worker",
        )
        return "failed"
    except Exception as exc:
        if staged is not None:  # free the space before recording the failure (the disk may be full)
            storage.drop_staging(staged)
            staged = None
        outage = outage_of(exc)
        if outage is not None:  # transient: given back to the queue, or failed with its own code once bounded
            return _outage(self, db, storage, job_id, worker, outage, settings)
        code, message = _explain(scrub_exception(exc, labels), job.upload_name)
        message = scrub_paths(message, labels)  # no server path in what a client reads
        if code == "internal_error":
            log.exception("job %s failed (%s)", job_id, code)
        else:
            log.info("job %s failed (%s): %s", job_id, code, exc)
        db.finish(job_id, worker, "failed", error_code=code, error_message=escape_control(message))
        return "failed"
    finally:
        if staged is not None:
            storage.drop_staging(staged)
        timer.log(job)


def _outage(task: Any, db: Database, storage: Any, job_id: str, worker: str, outage: Outage, settings: Settings) -> str:
    """The database or the store stayed down past ``outage_seconds``: the job goes back to the queue and its message
    is sent again after a backoff (an attempt that ends so is not counted against ``max_attempts``); after
    ``outage_requeues`` of them it fails with the outage's code (``database_unavailable``, ``storage_unavailable``),
    and its half-published versions are removed. Where the database itself is down, nothing can be recorded: the
    message comes back once the job's heartbeat is stale, and a worker claims it then."""
    try:
        given_back = db.outages(job_id)
        if given_back >= settings.outage_requeues:
            log.warning("job %s failed: %s still unreachable after %d re-queues", job_id, outage.kind, given_back)
            db.finish(job_id, worker, "failed", error_code=outage.code, error_message=outage.message())
            with contextlib.suppress(Exception):
                storage.retire(job_id, keep="")  # no version of a failed job is whole
            return "failed"
        db.release(job_id, worker, stage=f"waiting: the {outage.kind} is unreachable")
        delay = min(settings.outage_seconds * 2**given_back, 900.0) + random.uniform(0, 5)
    except Exception as exc:  # the database is down too: the heartbeat stops, the job becomes claimable when stale
        log.warning("job %s: could not record the %s outage (%s)", job_id, outage.kind, type(exc).__name__)
        delay = settings.stale_seconds + random.uniform(1, 5)
    log.info("job %s: %s unreachable (%s); re-queued, again in %.0f s", job_id, outage.kind, outage.seen, delay)
    task.apply_async(args=[job_id], task_id=job_id, countdown=delay, queue=settings.queue)
    return "requeued"


def _run(
    job: Any,
    upload: Path,
    staged: Path,
    holder: _Holder,
    settings: Settings,
    db: Database,
    timer: Timings | None = None,
) -> list[dict[str, Any]]:
    """Run the job (``engine.job.run_job``: the plan, the stages and the files, as the CLI runs it) into ``staged``
    on the worker's runtime (``worker.app.runtime_of``: device and budget resolved once per process), then a PACS
    job's DICOM objects; returns the output descriptions (``engine.export.files``: kind, media type and triangles of
    each)."""
    from engine.job import run_job

    timer = timer or Timings(log)  # the attempt's (reconstruct_job), or one of its own
    spec = job_spec_of(job)
    holder.progress("loading", 1.0)
    timer.lap("prepare")  # the imports above (a new worker's first job), the spec, the first beat
    fetch_source(db, job.id, upload)  # a DICOMweb job's series (worker.pacs)
    timer.lap("fetch_source")
    laps = _Laps(holder, timer)
    try:
        result = run_job(
            upload,
            staged,
            spec,
            runtime_of(settings),
            on_progress=laps,
            label="upload",
            shares=(LOAD_END, PIPELINE_END),
            predecoded=settings.decode_during_upload,  # the slices the API decoded as they arrived, if there
        )
    finally:  # read once: a rerun decodes the upload (and the disk gets its room back)
        remove_predecoded(upload)
    timer.lap("write_files")

    def dicom_files() -> dict[str, Path]:  # a PACS job's Encapsulated STL (worker.pacs; reads its PACS records)
        if result.plan == "scan":
            return write_dicom_model(db, job.id, upload, staged, result.volume)  # type: ignore[arg-type]
        return write_dicom_labels(db, job.id, upload, staged, result.report, result.volume)  # one per label

    extra = retrying(dicom_files, within=settings.outage_seconds, doing="writing the DICOM model")
    timer.lap("dicom_files")
    return _described({**result.paths, **extra}, result.report)


class _Laps:
    """The job's progress to the holder (percent) and its steps to the attempt's timings: ``load`` ends when
    meshing begins, ``reconstruct`` (the pipeline, or the label models) when the files begin."""

    def __init__(self, holder: _Holder, timer: Timings) -> None:
        self.holder, self.timer, self.stage = holder, timer, "loading"

    def __call__(self, stage: str, fraction: float) -> None:
        if stage != self.stage:
            if self.stage == "loading":
                self.timer.lap("load")
            if stage == "writing":
                self.timer.lap("reconstruct")
            self.stage = stage
        self.holder.progress(stage, max(100.0 * fraction, 1.0))


def _described(paths: dict[str, Path], report: Any) -> list[dict[str, Any]]:
    """The outputs' descriptions (``engine.export.files``: kind, media type and triangles of each)."""
    return [
        {
            "name": name,
            "kind": FILES[name].kind,
            "media_type": FILES[name].media_type,
            "bytes": path.stat().st_size,
            "triangles": triangle_count(name, report),
        }
        for name, path in paths.items()
    ]


@app.task(name="bonemesh.orient")
def orient_job(job_id: str, orient: dict[str, Any]) -> str:
    """Re-publish a succeeded job's outputs with the stack placed by ``orient`` (``engine.job.reorient``: no
    reconstruction): the outputs are copied into a staging folder, written again there and published in one rename
    (``Storage.publish``); the job's outputs, its params' ``orient`` and its stage (``orienting`` -> ``done``) follow.
    Idempotent: the orientation is absolute, so a redelivered message writes the same files; a job no longer
    re-orienting (deleted, or another message done first) is left alone."""
    from core.db import ORIENTING
    from engine.errors import InputError
    from engine.job import OrientParams
    from engine.job.reorient import read_report, reorient

    settings = get_settings()
    db = database(settings.db_url)
    storage = storage_from_settings(settings)
    job = db.get(job_id)
    version = version_of(job)
    has_report = job is not None and storage.output(job_id, "report.json", version) is not None
    if job is None or job.state != "succeeded" or job.stage != ORIENTING or not has_report:
        log.info("job %s: not being re-oriented; message dropped", job_id)
        return "skipped"
    staged = storage.staging_dir(job_id)
    try:
        if any(o["name"] == LABELS_ZIP for o in job.outputs or []):  # a label job (engine.labels): no print model
            raise InputError("a label job's models are placed by its label map (or are a CT's pieces): not re-oriented")
        storage.copy_outputs(job_id, version, staged)
        wanted = OrientParams(**orient)
        runtime = runtime_of(settings)
        paths = reorient(staged, wanted, device=runtime.backend, max_device_bytes=runtime.budget)
        report = read_report(staged)
        outputs = [
            {**o, "bytes": (staged / o["name"]).stat().st_size, "triangles": triangle_count(o["name"], report)}
            if o["name"] in paths
            else o
            for o in job.outputs or []
        ]
        new_version = storage.publish(job_id, staged)  # invisible until finish_orient records it
        outputs = [{**o, "version": new_version} for o in outputs]
        params = {**job.params, "orient": dict(orient)}
        engine_params = None
        if job.engine_params:
            engine_params = {**job.engine_params, "recon": {**job.engine_params["recon"], "orient": dict(orient)}}
        values: dict[str, Any] = {"outputs": outputs, "params": params}
        if engine_params is not None:
            values["engine_params"] = engine_params
        if db.finish_orient(job_id, **values):
            storage.retire(job_id, keep=new_version)
        return "succeeded"
    except Exception as exc:
        storage.drop_staging(staged)
        known = isinstance(exc, InputError | TypeError | ValueError)
        if not known:
            log.exception("job %s: re-orientation failed", job_id)
        message = str(exc) if known else f"the re-orientation failed ({type(exc).__name__}); the model is unchanged"
        db.finish_orient(
            job_id,
            error_code="orient_failed",
            error_message=escape_control(scrub_paths(message, {str(staged): "the job's outputs"})),
        )
        return "failed"


def job_spec_of(job: Any) -> JobSpec:
    """The job's specification as the API validated and stored it (``engine.job.JobSpec.to_dict``). A job recorded
    by an older release kept only ``recon`` and ``spacing_zyx_mm`` (or nothing) in its engine form: what the input
    is comes again from its client parameters (``core.params.JobParams.job_spec``)."""
    from engine.job import JobSpec

    engine = getattr(job, "engine_params", None)
    if engine and "input" in engine:
        return JobSpec.from_dict(engine)
    from core.params import JobParams  # an older record: the client's form

    client = JobParams.model_validate(getattr(job, "params", None) or {}).job_spec()
    if not engine:
        return client
    stored = JobSpec.from_dict(engine)
    spacing = stored.input.spacing_zyx_mm
    return dataclasses.replace(stored, input=dataclasses.replace(client.input, spacing_zyx_mm=spacing))


def _explain(exc: Exception, filename: str) -> tuple[str, str]:
    """An error code and a message a clinician can act on."""
    from engine.errors import (
        EmptySurfaceError,
        IncompleteSeriesError,
        InputError,
        NoSpacingError,
        PrintCheckError,
        StageError,
    )

    if is_storage_full(exc):
        return "storage_full", (
            "the worker could not write the models: its data volume is full; nothing was published. Try again "
            "later, or ask the operator to free space"
        )
    if isinstance(exc, SourceIncomplete):
        shown = ", ".join(exc.missing[:3]) + (", ..." if len(exc.missing) > 3 else "")
        return "source_incomplete", (
            f"{exc}; nothing was reconstructed or delivered. Missing SOP Instance UIDs: {shown}. Check the series "
            "on the server (or that it can send them as stored: transfer-syntax=*), then submit the job again"
        )
    if isinstance(exc, SourceUnavailable):
        return "source_unavailable", str(exc)
    if isinstance(exc, PrintCheckError):
        return "print_check", f"the print model failed its check and was not published: {exc}"
    if isinstance(exc, EmptySurfaceError):
        return "no_surface", relabel(str(exc), filename)
    if isinstance(exc, IncompleteSeriesError | UncheckedSource):
        return "incomplete_series", relabel(str(exc), filename)
    if isinstance(exc, NoSpacingError):
        return "no_spacing", (
            f'{filename}: the image slices do not say how large a voxel is; send "spacing": [z, y, x] in '
            "millimetres in the job's params"
        )
    if isinstance(exc, InputError):
        return "bad_input", relabel(str(exc), filename)
    if isinstance(exc, MemoryError):
        return "too_large", "the scan needs more memory than this worker has; crop or downsample it"
    if isinstance(exc, StageError):
        return "internal_error", f"the reconstruction failed in stage '{exc.stage}'; the team has the details"
    return "internal_error", f"the reconstruction failed unexpectedly ({type(exc).__name__}); the team has the details"
