"""The Celery application of the worker: one job at a time per process (one per GPU), late acknowledgement, a
lost worker's message is rejected back to the queue, soft and hard time limits.

Importing this module never imports Warp: the engine is imported inside the task, i.e. in the pool's child
process after the fork, so CUDA is initialised there and never in the parent.
"""

from __future__ import annotations

import functools
import multiprocessing
import multiprocessing.process
import os
from typing import TYPE_CHECKING

from celery import Celery
from celery.signals import worker_process_init

from core.logsafe import safe_logger
from core.queue import celery_config
from core.settings import Settings, get_settings

if TYPE_CHECKING:
    from engine.job import Runtime

log = safe_logger("bonemesh.worker")
WARMUP_TIMEOUT_S = 300  # how long the pool waits for a child's start (its warm-up included)


def make_app() -> Celery:
    settings = get_settings()
    app = Celery("bonemesh-worker", include=["worker.tasks"])
    app.conf.update(
        celery_config(settings.redis_url, settings.queue),
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        worker_concurrency=1,
        task_soft_time_limit=settings.job_soft_time_limit,
        task_time_limit=settings.job_time_limit,
        worker_max_tasks_per_child=50,
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
        worker_proc_alive_timeout=WARMUP_TIMEOUT_S,
    )
    return app


app = make_app()


@worker_process_init.connect
def _allow_children(**_: object) -> None:
    """Celery's pool children are daemonic, and a daemonic process may not start processes; the decimation stage
    runs MeshLab in a process pool and DICOM ingest decodes in processes (``engine.io.procs``), so the child drops
    the flag (its own children are reaped by those pools). Billiard also makes its own process the standard
    library's current process, with an authentication key that refuses to be pickled outside billiard: a fork
    server or spawn start (what ``engine.io.procs`` uses) pickles it, so the child's key becomes the standard
    library's kind, with the same bytes."""
    current = multiprocessing.current_process()
    current._config["daemon"] = False  # the setter refuses on a started process
    current._config["authkey"] = multiprocessing.process.AuthenticationString(bytes(current.authkey))


@functools.cache
def _runtime(
    device: str, max_device_bytes: str | None, png_decoder: str, threads: int | None, processes: bool | None
) -> Runtime:
    from engine.job import resolve_runtime

    host = os.environ.get("BONEMESH_MAX_HOST_BYTES")  # the host memory bound per job (engine.budget)
    return resolve_runtime(
        device,
        max_device_bytes,
        png_decoder=png_decoder,
        decode_threads=threads,
        decode_processes=processes,
        max_host_bytes=host,
    )


def runtime_of(settings: Settings) -> Runtime:
    """The worker process's runtime (``engine.job.Runtime``: backend, device, budget, decoders), resolved once from
    its settings (``BONEMESH_DEVICE`` ``auto`` included) and used by its warm-up and every job.

    Raises:
        ValueError: the device is not present (the reason names it).
    """
    return _runtime(
        settings.device,
        settings.max_device_bytes,
        settings.png_decoder,
        settings.decode_threads,
        settings.decode_processes,
    )


def warms_up(settings: Settings) -> bool:
    """Whether the worker warms its device up at start: unless ``BONEMESH_WARMUP`` is false, on every device (a
    GPU's context and modules, an OpenCL context's programs, Warp's CPU modules: 1.3 s on the 2-core CI machine,
    which a CPU worker's first job took longer without it)."""
    return settings.warmup != "false"


@worker_process_init.connect
def _warm_device(**_: object) -> None:
    """One small job on the device before the first real one (``engine.job.warmup``); a failure is logged, and the
    first job then pays for what was not warmed (or fails with its own reason)."""
    settings = get_settings()
    try:
        runtime = runtime_of(settings)  # resolved once: the warm-up and every job use exactly this
    except ValueError as exc:
        log.error("device %s is not usable: %s; this worker's jobs fail until it is", settings.device, exc)
        return
    log.info("%s", runtime.describe())
    if not warms_up(settings):
        return
    try:
        from engine.job import mib, warm_up

        info = warm_up(runtime, volume_bytes=settings.warmup_volume_bytes, png_rows=settings.png_decoder == "auto")
    except Exception as exc:
        log.warning("warm-up failed on %s: %s", runtime.spec, exc)
        return
    pinned = mib(info["pinned_bytes"])
    log.info("device %s warm in %.2f s (%s page-locked for loads)", info["device"], info["seconds"], pinned)
