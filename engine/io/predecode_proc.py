"""The decoding of an upload's slices as it arrives (``engine.io.predecode``) in a child process of its own.

The API's receiving thread writes the upload's file and, per batch, tells the child how many bytes of it are now
on disk (:meth:`DecoderProcess.advance`: one short line written to a pipe without waiting; where the pipe is full
the line is skipped, a later one says more). The child reads the file as it grows and feeds those bytes to the same
:class:`engine.io.predecode.UploadDecoder` (its threads in the child): the parsing and decoding no longer share the
API process and its GIL with the upload's receiving loop. :meth:`DecoderProcess.finish` (the upload committed)
tells the child its length and waits, at most ``wait_seconds``, for its verdict: the child feeds the rest, does
the decoder's own finish checks and writes the manifest (kept) or removes the sidecar. :meth:`DecoderProcess.abort`
kills the child and removes the sidecar. A child that dies, hangs or answers nonsense is killed and its files
removed: the upload goes on and the worker decodes the zip, as when the decoder stops. A child whose API is gone
(its stdin closed) removes its files and exits.

:class:`DecoderChildren` keeps one child started and waiting (its interpreter and ``engine.io.predecode``
imported, about 0.2 s of CPU), so an upload does not wait for a start: each child decodes one upload and exits,
and the next is started when one is done with (the first upload, and a second one at the same time, start their
own). Children are started with ``subprocess`` (fork and exec at once: safe
from a process with threads), in a session of their own (a terminal's Ctrl-C goes to the API, which ends them).
The child imports ``engine.io.predecode`` only (no Warp).

Protocol (text lines): the parent sends ``{"upload": ..., "part": ..., "threads": ..., "layout": ...}`` (JSON: where
the upload will be committed, the file it is written to meanwhile, the decoding threads, the sidecar's layout), then
``<bytes on disk>`` lines, then ``finish <length>``; the child answers ``{"kept": ..., "reason": ..., "slices": ...,
"feed_s": ..., "finish_s": ...}`` once (the last two: its feeding and its finishing left when the finish came), and
exits.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from engine.io.predecode import PLANES, remove_predecoded

__all__ = ["DecoderChildren", "DecoderProcess", "main"]

READ_BYTES = 8 << 20  # the child's reads of the upload file (fresh bytes each: the decoder keeps views of them)
WAIT_SECONDS = 60.0  # the API's wait for a child's verdict once the upload is complete


def _spawn() -> subprocess.Popen[bytes]:
    root = str(Path(__file__).resolve().parents[2])  # where ``engine`` is importable from
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
    return subprocess.Popen(
        [sys.executable, "-m", "engine.io.predecode_proc"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        env=env,
        cwd=root,
        close_fds=True,
        start_new_session=True,
    )


class DecoderProcess:
    """One upload's decoding in a child (see the module docstring). ``advance``, ``finish`` and ``abort`` never
    raise; ``reason`` says why nothing was kept, ``slices`` how many slices were decoded."""

    def __init__(
        self,
        proc: subprocess.Popen[bytes],
        upload: Path,
        wait_seconds: float = WAIT_SECONDS,
        on_done: Callable[[], None] | None = None,
    ) -> None:
        self.proc = proc
        self.on_done = on_done  # called once, when the child is done with (ended or exiting)
        self.upload = Path(upload)
        self.wait_seconds = wait_seconds
        self.reason: str | None = None
        self.slices = 0
        self.timings: dict[str, float] = {}  # waited (the API, for the verdict), feed and finish (the child's)
        self.told = 0
        self.done = False
        self.completed: float | None = None  # when the child was told the upload is complete (``complete``)
        assert proc.stdin is not None and proc.stdout is not None
        self._in: IO[bytes] = proc.stdin
        self._out: IO[bytes] = proc.stdout
        os.set_blocking(self._in.fileno(), False)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def _send(self, line: bytes) -> bool:
        """Write one line (shorter than a pipe's atomic write) at once, or not at all (False)."""
        try:
            return os.write(self._in.fileno(), line) == len(line)
        except BlockingIOError:
            return False
        except (OSError, ValueError):  # the child is gone: finish finds out
            return False

    def start(self, part: Path, threads: int, layout: str = PLANES) -> bool:
        job = {"upload": str(self.upload), "part": str(part), "threads": threads, "layout": layout}
        return self._send(json.dumps(job).encode() + b"\n")

    def advance(self, on_disk: int) -> None:
        """The upload's first ``on_disk`` bytes are in its file (O(1), never waits)."""
        if on_disk > self.told and not self.done and self._send(b"%d\n" % on_disk):
            self.told = on_disk

    def complete(self, length: int) -> None:
        """The upload is complete (``length`` bytes, committed at ``upload``): tell the child now (O(1), never
        waits; where the pipe is full, ``finish`` tells it), so that it finishes its slices and checks the archive
        while the API inspects the upload; ``finish`` then waits for its verdict."""
        if not self.done and self.completed is None and self._send(b"finish %d\n" % length):
            self.completed = time.monotonic()

    def finish(self, length: int) -> bool:
        """The upload is complete (``length`` bytes, committed at ``upload``): True where the child kept the sidecar
        (its manifest written), else False, the child ended and its files removed."""
        if self.done:
            return False
        deadline = time.monotonic() + self.wait_seconds
        try:
            self.complete(length)
            while self.completed is None:  # the pipe was full: wait for room
                if self.proc.poll() is not None:
                    raise _Gone(f"the decoding process ended ({self.proc.returncode})")
                if not select.select([], [self._in.fileno()], [], max(0.0, deadline - time.monotonic()))[1]:
                    raise _Gone(f"the decoding process took no order in {self.wait_seconds:g} s")
                self.complete(length)
            verdict = json.loads(self._verdict(deadline))
            self.timings = {"waited_s": round(time.monotonic() - self.completed, 4)}
            self.timings.update({k: float(verdict[k]) for k in ("feed_s", "finish_s") if k in verdict})
            kept = verdict["kept"] is True
            self.reason = None if kept else str(verdict.get("reason") or "not kept")
            self.slices = int(verdict.get("slices") or 0) if kept else 0
        except Exception as exc:
            self.reason = str(exc) if isinstance(exc, _Gone) else f"the decoding process: {type(exc).__name__}: {exc}"
            kept = False
        self.done = True
        if kept:  # its manifest is written: the child only exits now
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._kill()
        else:
            self._kill()
            remove_predecoded(self.upload)
        self._close()
        return kept

    def _verdict(self, deadline: float) -> bytes:
        fd, got = self._out.fileno(), b""
        while not got.endswith(b"\n"):
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise _Gone(f"the decoding process gave no verdict in {self.wait_seconds:g} s")
            piece = os.read(fd, 4096)
            if not piece:
                raise _Gone(f"the decoding process ended ({self.proc.wait()}) without a verdict")
            got += piece
            if len(got) > 1 << 16:
                raise _Gone("the decoding process's verdict is too long")
        return got

    def abort(self) -> None:
        """Kill the child and remove the sidecar (a refused upload keeps nothing)."""
        self.reason = self.reason or "aborted"
        self.done = True
        self._kill()
        remove_predecoded(self.upload)
        self._close()

    def _kill(self) -> None:
        """End the child (SIGKILL) and wait for it: none of its writes can land after this."""
        with contextlib.suppress(OSError):
            self.proc.kill()
        with contextlib.suppress(Exception):
            self.proc.wait(timeout=10)

    def _close(self) -> None:
        for pipe in (self._in, self._out):
            with contextlib.suppress(OSError):
                pipe.close()
        done, self.on_done = self.on_done, None
        if done is not None:
            done()


class _Gone(Exception):
    """The child did not answer as it should."""


class DecoderChildren:
    """Started children waiting for an upload (one at a time), handed out by :meth:`start`; :meth:`close` ends the
    waiting one. Thread-safe."""

    def __init__(self, wait_seconds: float = WAIT_SECONDS) -> None:
        self.wait_seconds = wait_seconds
        self._lock = threading.Lock()
        self._spare: subprocess.Popen[bytes] | None = None
        self._closed = False

    def start(self, upload: Path, part: Path, threads: int, layout: str = PLANES) -> DecoderProcess | None:
        """A child decoding the upload being written to ``part`` (to be committed at ``upload``) into a sidecar of
        ``layout`` (``engine.io.predecode``), or None where it could not be started."""
        with self._lock:
            if self._closed:
                return None
            proc, self._spare = self._spare, None
        if proc is None or proc.poll() is not None:
            proc = _spawn()
        child = DecoderProcess(proc, upload, self.wait_seconds, on_done=self._refill_later)
        if not child.start(part, threads, layout):
            child.abort()
            return None
        return child

    def _refill_later(self) -> None:
        """Start the next child once this upload is done, on a thread: its start (about 0.2 s of CPU) does not
        compete with the upload and its decoding, and the upload's answer does not wait for it."""
        threading.Thread(target=self._refill, daemon=True, name="predecode-spare").start()

    def _refill(self) -> None:
        spare: subprocess.Popen[bytes] | None
        try:
            spare = _spawn()
        except OSError:
            return
        with self._lock:
            if self._spare is None and not self._closed:
                self._spare, spare = spare, None
        if spare is not None:
            _end(spare)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            spare, self._spare = self._spare, None
        if spare is not None:
            _end(spare)


def _end(proc: subprocess.Popen[bytes]) -> None:
    with contextlib.suppress(OSError):
        proc.kill()
    with contextlib.suppress(Exception):
        proc.wait(timeout=10)
    for pipe in (proc.stdin, proc.stdout):
        if pipe is not None:
            with contextlib.suppress(OSError):
                pipe.close()


class _Orders:
    """What the parent said so far (read from stdin on a thread of the child)."""

    def __init__(self, stream: IO[bytes]) -> None:
        self.on_disk = 0
        self.length: int | None = None  # finish's
        self.finish_at: float | None = None  # when it came (time.monotonic)
        self.gone = False  # stdin closed, or a line not understood: abort
        self.cond = threading.Condition()
        self.stream = stream
        threading.Thread(target=self._read, daemon=True, name="orders").start()

    def _read(self) -> None:
        try:
            for line in self.stream:
                word, _, rest = line.strip().partition(b" ")
                with self.cond:
                    if word == b"finish":
                        self.length, self.finish_at = int(rest), time.monotonic()
                    else:
                        self.on_disk = max(self.on_disk, int(word))
                    self.cond.notify_all()
        except Exception:
            pass
        with self.cond:
            self.gone = True
            self.cond.notify_all()

    def wait_past(self, at: int) -> tuple[int, bool]:
        """(bytes there to read, whether that is all of them) once there are bytes past ``at`` or it is all."""
        with self.cond:
            while not self.gone and self.length is None and self.on_disk <= at:
                self.cond.wait()
            if self.gone:
                return at, False
            if self.length is not None:
                return self.length, True
            return self.on_disk, False


def _open(part: str, upload: str) -> int | None:
    """The upload's file: where it is written, or where it was committed (renamed: the same file)."""
    for path in (part, upload):
        with contextlib.suppress(FileNotFoundError):
            return os.open(path, os.O_RDONLY)
    return None


def main() -> None:
    """The child (``python -m engine.io.predecode_proc``)."""
    from engine.io.predecode import UploadDecoder

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the API ends it
    line = sys.stdin.buffer.readline()
    if not line:
        return
    job = json.loads(line)
    decoder = UploadDecoder(Path(job["upload"]), threads=int(job["threads"]), layout=job.get("layout", PLANES))
    orders = _Orders(sys.stdin.buffer)
    fd: int | None = None
    at = 0
    while True:
        target, last = orders.wait_past(at)
        if orders.gone:  # the API is gone, or said nonsense: keep nothing
            decoder.abort()
            return
        if fd is None and target > at:  # the file has bytes: it is there
            fd = _open(job["part"], job["upload"])
            if fd is None:
                decoder.stop("the upload's file is gone")
        while fd is not None and at < target and not decoder.stopped:
            chunk = os.pread(fd, min(READ_BYTES, target - at), at)
            if not chunk:
                decoder.stop(f"the upload's file ends at {at} bytes, not {target}")
                break
            decoder.feed([chunk])
            at += len(chunk)
        if last:
            break
        if decoder.stopped:
            at = max(at, target)  # read no more: wait for the finish
    fed = time.monotonic()
    if fd is not None:
        os.close(fd)
    kept = decoder.finish()
    slices = sum(bool(m["png"]) for m in decoder.members) if kept else 0
    verdict: dict[str, Any] = {"kept": kept, "reason": decoder.reason, "slices": slices}
    verdict["feed_s"] = round(max(0.0, fed - (orders.finish_at or fed)), 4)  # feeding left when the upload was complete
    verdict["finish_s"] = round(time.monotonic() - fed, 4)  # the decoding left, the checks and the manifest
    sys.stdout.buffer.write(json.dumps(verdict).encode() + b"\n")
    sys.stdout.buffer.flush()


if __name__ == "__main__":
    try:
        main()
    except BaseException:
        import traceback

        traceback.print_exc()
        os._exit(1)
    os._exit(0)  # not waiting for the thread reading stdin
