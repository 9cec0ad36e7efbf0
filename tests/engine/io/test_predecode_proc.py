"""The decoding during the upload in a child process (``engine.io.predecode_proc``): told how much of the growing
upload file is on disk, in any steps, the child leaves the sidecar the in-process decoder leaves (the same planes
byte for byte, the same manifest); a child killed, hung or cut off from its parent, an abort, and an archive it
cannot vouch for leave nothing, within the bounded wait; a started child waits for the next upload; the child
loads no Warp."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.io.predecode import PLANES, ROWS, UploadDecoder, sidecar_paths
from engine.io.predecode_proc import DecoderChildren, DecoderProcess
from tests.engine.io.test_predecode import _named, _nothing_left, _pngs, _same_as_loader, _zip

ROOT = Path(__file__).resolve().parents[3]


def _upload_through_child(
    folder: Path, data: bytes, chunk: int, children: DecoderChildren, *, finish: bool = True, layout: str = PLANES
) -> tuple[DecoderProcess, Path]:
    """Write ``data`` into a part file in ``chunk``-byte pieces, telling a child after each, then commit it (the
    part renamed to ``upload``) and finish, as the API does."""
    folder.mkdir(parents=True, exist_ok=True)
    upload, part = folder / "upload", folder / ".upload-x.part"
    child = children.start(upload, part, 2, layout)
    assert child is not None
    with part.open("wb") as fh:
        for i in range(0, len(data), chunk):
            fh.write(data[i : i + chunk])
            fh.flush()
            child.advance(min(i + chunk, len(data)))
    os.replace(part, upload)
    if finish:
        child.finish(len(data))
    return child, upload


def _in_process(folder: Path, data: bytes, layout: str = PLANES) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    upload = folder / "upload"
    upload.write_bytes(data)
    dec = UploadDecoder(upload, threads=2, layout=layout)
    dec.feed([data])
    assert dec.finish(), dec.reason
    return upload


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False  # a zombie still counts: Popen.wait reaps it


@pytest.fixture
def children() -> Iterator[DecoderChildren]:
    pool = DecoderChildren(wait_seconds=30)
    yield pool
    pool.close()


@pytest.mark.parametrize(
    ("method", "streamed"),
    [(zipfile.ZIP_STORED, False), (zipfile.ZIP_DEFLATED, True)],
    ids=["stored", "deflated-descriptor"],
)
@pytest.mark.parametrize("chunk", [1, 7, 4099, 1 << 30], ids=["1B", "7B", "4099B", "whole"])
def test_the_childs_sidecar_is_the_in_process_decoders(
    tmp_path: Path, children: DecoderChildren, method: int, streamed: bool, chunk: int
) -> None:
    data = _zip(_named(_pngs(9, (33, 21))), method=method, streamed=streamed)
    child, upload = _upload_through_child(tmp_path / "child", data, chunk, children)
    assert child.reason is None and child.slices == 9
    ref = _in_process(tmp_path / "threads", data)
    for got, want in zip(sidecar_paths(upload), sidecar_paths(ref), strict=True):
        assert got.read_bytes() == want.read_bytes(), got.name
    _same_as_loader(upload)
    assert child.proc.poll() is not None  # one upload, then it exits


@pytest.mark.parametrize("layout", [PLANES, ROWS])
def test_the_bundled_scan_through_a_child(tmp_path: Path, children: DecoderChildren, layout: str) -> None:
    data = HEADSQ_ZIP.read_bytes()
    child, upload = _upload_through_child(tmp_path / "child", data, 65_537, children, layout=layout)
    assert child.slices == 93, child.reason
    ref = _in_process(tmp_path / "threads", data, layout)
    assert json.loads(sidecar_paths(upload)[1].read_text()) == json.loads(sidecar_paths(ref)[1].read_text())
    assert sidecar_paths(upload)[0].read_bytes() == sidecar_paths(ref)[0].read_bytes()
    _same_as_loader(upload, HEADSQ_SPACING_ZYX_MM)


def test_what_it_cannot_vouch_for_leaves_nothing(tmp_path: Path, children: DecoderChildren) -> None:
    data = _zip([*_named(_pngs(4)), ("scan/slice_009.png", _pngs(1, (8, 8), seed=3)[0])])  # a slice of another shape
    child, upload = _upload_through_child(tmp_path, data, 1000, children)
    assert child.reason is not None and "unlike the slices before it" in child.reason
    assert _nothing_left(upload)


@pytest.mark.parametrize("how", ["killed", "hung"])
def test_a_child_killed_or_hung_never_holds_the_upload(tmp_path: Path, how: str) -> None:
    children = DecoderChildren(wait_seconds=1.0)
    try:
        data = _zip(_named(_pngs(12, (64, 64))))
        child, upload = _upload_through_child(tmp_path, data[: len(data) // 2], 997, children, finish=False)
        os.kill(child.pid, signal.SIGKILL if how == "killed" else signal.SIGSTOP)
        with upload.open("ab") as fh:
            fh.write(data[len(data) // 2 :])
        child.advance(len(data))  # a dead child's pipe: no error
        t0 = time.monotonic()
        assert child.finish(len(data)) is False
        assert time.monotonic() - t0 < 5
        assert child.reason and "decoding process" in child.reason
        assert _nothing_left(upload) and _gone(child.pid)
    finally:
        children.close()


def test_abort_kills_it_and_keeps_nothing(tmp_path: Path, children: DecoderChildren) -> None:
    data = _zip(_named(_pngs(12, (64, 64))))
    child, upload = _upload_through_child(tmp_path, data[: len(data) * 2 // 3], 1 << 12, children, finish=False)
    deadline = time.monotonic() + 10
    while not sidecar_paths(upload)[0].exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert sidecar_paths(upload)[0].exists()  # it had begun
    child.abort()
    assert _nothing_left(upload) and _gone(child.pid)
    assert child.finish(len(data)) is False


def test_told_early_it_checks_beside_the_api_and_the_verdict_is_the_same(
    tmp_path: Path, children: DecoderChildren
) -> None:
    """``complete`` right after the commit: the child finishes while the API inspects (here: waits), ``finish``
    only collects its verdict, the same sidecar as when told by ``finish``; told early, then aborted (the
    inspection refused the upload), nothing is left."""
    data = _zip(_named(_pngs(9, (33, 21))))
    child, upload = _upload_through_child(tmp_path / "early", data, 4099, children, finish=False)
    child.complete(len(data))
    deadline = time.monotonic() + 20
    while not sidecar_paths(upload)[1].exists() and time.monotonic() < deadline:  # the manifest, before finish
        time.sleep(0.01)
    assert sidecar_paths(upload)[1].exists()
    assert child.finish(len(data)) is True and child.slices == 9
    ref = _in_process(tmp_path / "threads", data)
    for got, want in zip(sidecar_paths(upload), sidecar_paths(ref), strict=True):
        assert got.read_bytes() == want.read_bytes(), got.name
    child, upload = _upload_through_child(tmp_path / "refused", data, 4099, children, finish=False)
    child.complete(len(data))
    child.abort()
    assert _nothing_left(upload) and _gone(child.pid)


def test_a_child_whose_api_is_gone_removes_its_files(tmp_path: Path, children: DecoderChildren) -> None:
    data = _zip(_named(_pngs(12, (64, 64))))
    child, upload = _upload_through_child(tmp_path, data[: len(data) // 2], 1 << 12, children, finish=False)
    child.proc.stdin.close()  # type: ignore[union-attr]
    assert child.proc.wait(timeout=20) == 0
    assert _nothing_left(upload)
    child.abort()


def test_a_child_waits_for_the_next_upload(tmp_path: Path) -> None:
    children = DecoderChildren()
    try:
        first = children.start(tmp_path / "a" / "upload", tmp_path / "a" / "part", 1)
        assert first is not None and children._spare is None  # not while an upload is decoded
        first.abort()  # done with: the next one is started (on a thread)
        deadline = time.monotonic() + 10
        while (spare := children._spare) is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert spare is not None and spare.poll() is None
        second = children.start(tmp_path / "b" / "upload", tmp_path / "b" / "part", 1)
        assert second is not None and second.proc is spare  # the one started ahead
        second.abort()
        deadline = time.monotonic() + 10
        while (last := children._spare) is None and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        children.close()
    assert last is not None and last.poll() is not None  # close ends the waiting one
    assert children.start(tmp_path / "c" / "upload", tmp_path / "c" / "part", 1) is None


def test_the_child_loads_no_warp() -> None:
    code = "import sys, engine.io.predecode_proc as m; print('warp' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stderr
