"""The API process's background threads: the reconciler (re-enqueue jobs whose broker message is gone, or whose
worker stopped sending heartbeats: the job records are the truth), the webhook sender (:mod:`service.webhooks`)
the sweep of what killed publishes left (:func:`sweep_outputs`), the sweep of expired ``Idempotency-Key`` values
(:mod:`service.idempotency`) and, with S3 storage, the sweep of direct uploads
not completed in time (:func:`service.direct.sweep`). All are
plain threads (their work is blocking database and network calls), stopped with the app."""

from __future__ import annotations

import datetime as dt
import threading
from collections.abc import Callable

from core.db import utcnow
from core.logsafe import safe_logger
from service.direct import sweep
from service.services import Services
from service.webhooks import deliver_due

log = safe_logger("bonemesh.api")


def reconcile(svc: Services) -> dict[str, int]:
    """Re-enqueue lost jobs: running with a stale heartbeat, or queued without a message in the broker."""
    s = svc.settings
    now = utcnow()
    queued, stale = svc.db.lost_jobs(
        queued_before=now - dt.timedelta(seconds=s.reconcile_seconds),
        stale_before=now - dt.timedelta(seconds=s.stale_seconds),
    )
    requeued = 0
    for job_id in stale:
        if svc.db.requeue_stale(job_id, now - dt.timedelta(seconds=s.stale_seconds)):
            log.warning("job %s: its worker stopped (no heartbeat for %gs); re-queued", job_id, s.stale_seconds)
            requeued += svc.enqueue(job_id)
    resent = 0
    if queued:
        present = svc.queue.jobs_in_broker()
        for job_id in queued:
            if job_id not in present:
                log.warning("job %s: queued but its message is not in the broker; re-sent", job_id)
                resent += svc.enqueue(job_id)
    return {"requeued_stale": requeued, "resent": resent}


def sweep_outputs(svc: Services) -> int:
    """What publishes killed half way left, begun more than ``upload_ttl_seconds`` ago (a publish takes seconds:
    anything that old belongs to no live attempt); the next attempt's ``retire`` removes it sooner."""
    cutoff = (utcnow() - dt.timedelta(seconds=svc.settings.upload_ttl_seconds)).replace(tzinfo=dt.UTC)
    gone = svc.storage.sweep_outputs(cutoff)
    if gone:
        log.info("swept %d unfinished output upload(s) of killed publishes", gone)
    return gone


class Background:
    """The reconciler and the webhook sender, each in a daemon thread until ``stop``.

    Args:
        svc: the services they work on.
    """

    def __init__(self, svc: Services) -> None:
        self.svc = svc
        self._stop = threading.Event()
        s = svc.settings
        self._threads = [
            threading.Thread(target=self._loop, args=("reconciler", s.reconcile_seconds, self._reconcile), daemon=True),
            threading.Thread(target=self._loop, args=("webhooks", s.webhook_poll_seconds, self._webhooks), daemon=True),
        ]
        if svc.storage.direct is not None:  # as often as the reconciler: one listing of the store's uploads a round
            loop = ("uploads", s.reconcile_seconds, self._uploads)
            self._threads.append(threading.Thread(target=self._loop, args=loop, daemon=True))
        keys = ("idempotency keys", s.reconcile_seconds, self._keys)
        self._threads.append(threading.Thread(target=self._loop, args=keys, daemon=True))
        outputs = ("outputs", s.reconcile_seconds, self._outputs)  # one listing of unfinished output uploads a round
        self._threads.append(threading.Thread(target=self._loop, args=outputs, daemon=True))

    def _reconcile(self) -> None:
        reconcile(self.svc)

    def _webhooks(self) -> None:
        deliver_due(self.svc)

    def _uploads(self) -> None:
        sweep(self.svc)

    def _keys(self) -> None:
        gone = self.svc.db.sweep_keys(utcnow())
        if gone:
            log.info("forgot %d expired Idempotency-Key value(s)", gone)

    def _outputs(self) -> None:
        sweep_outputs(self.svc)

    def _loop(self, name: str, every: float, step: Callable[[], None]) -> None:
        while not self._stop.wait(every):
            try:
                step()
            except Exception as exc:  # Redis or the database down for a moment: try again next round
                log.warning("%s: %s", name, exc)

    def start(self) -> None:
        for thread in self._threads:
            thread.start()

    def stop(self) -> None:
        self._stop.set()
