"""Errors are told apart by their type, never by their text: the engine raises ``NotAScanError`` and
``NoSpacingError`` where it finds those cases, the API answers 415 / 422 by type (``service.upload_check``) and the
worker picks ``no_spacing`` / ``bad_input`` by type (``worker.tasks._explain``). Each check also sends a message
that reads like the other kind, to show the text plays no part."""

from __future__ import annotations

import io
import tarfile
import zipfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import tifffile

from core.params import JobParams
from engine.errors import InputError, NoSpacingError, NotAScanError
from engine.io import inspect_input, load_volume
from service import upload_check
from service.uploads import UploadError


def _zip(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _png(value: int) -> bytes:
    return iio.imwrite("<bytes>", np.full((16, 16), value, np.uint8), extension=".png")


def _write(tmp_path: Path, name: str, data: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


def test_the_engine_raises_not_a_scan_for_what_is_no_scan_container(tmp_path: Path) -> None:
    tgz = io.BytesIO()
    with tarfile.open(fileobj=tgz, mode="w:gz") as tf:
        noise = np.random.default_rng(0).integers(0, 256, 1 << 16, np.uint8).tobytes()
        for k in range(4):
            info = tarfile.TarInfo(f"{k}.png")
            info.size = len(noise)
            tf.addfile(info, io.BytesIO(noise))
    not_scans = {
        "text.bin": b"hello, not a scan",  # neither an archive nor a volume file
        "slice.png": _png(7),  # one 2-D image
        "cut.zip": _zip({"a.png": _png(1)})[:40],  # ends in .zip, not a readable zip
        "cut.tar.gz": tgz.getvalue()[: len(tgz.getvalue()) // 2],  # a tar that opens, then cannot be read
    }
    for name, data in not_scans.items():
        with pytest.raises(NotAScanError):
            inspect_input(_write(tmp_path, name, data))
    other = {  # refused, but as something else: a 422 at the API
        "notes.zip": _zip({"notes.txt": b"no images here"}),
        "garbage.tar.gz": b"\x1f\x8b\x08\x00" + bytes(40),  # a tar by its name only (422, as before)
        "evil.zip": _zip({"../../evil.png": _png(1)}),
    }
    for name, data in other.items():
        with pytest.raises(InputError) as got:
            inspect_input(_write(tmp_path, name, data))
        assert not isinstance(got.value, NotAScanError), (name, got.value)


def test_the_engine_raises_no_spacing_for_a_stack_without_a_voxel_size(tmp_path: Path) -> None:
    pngs = _write(tmp_path, "pngs.zip", _zip({f"{k:03d}.png": _png(k) for k in range(8)}))
    with pytest.raises(NoSpacingError, match="does not carry its voxel size"):
        load_volume(pngs)
    assert load_volume(pngs, spacing_zyx_mm=(1.0, 0.5, 0.5)).spacing_zyx_mm == (1.0, 0.5, 0.5)
    tiff = tmp_path / "pixels_only.tif"  # the pixel size in its tags, no slice spacing
    tifffile.imwrite(tiff, np.zeros((8, 16, 16), np.uint8), resolution=(20.0, 20.0), resolutionunit="CENTIMETER")
    with pytest.raises(NoSpacingError, match="not the slice spacing"):
        load_volume(tiff)


@pytest.mark.parametrize(
    ("raised", "status"),
    [
        (NotAScanError("upload: some reason in words of its own"), 415),
        (InputError("upload is not a readable zip archive; single 2-D image; neither an archive"), 422),
        (NoSpacingError("upload: not a readable archive"), 422),
    ],
)
def test_the_api_answers_415_or_422_by_the_error_type(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, raised: InputError, status: int
) -> None:
    def refuse(path: object, limits: object = None) -> None:
        raise raised

    monkeypatch.setattr("engine.io.inspect_input", refuse)
    with pytest.raises(UploadError) as got:
        upload_check.inspect_upload(tmp_path / "upload", "scan.zip", JobParams())
    assert got.value.status == status
    assert got.value.detail == str(raised).replace("upload", "scan.zip", 1)  # the engine's message, relabelled


def test_the_api_answers_415_for_real_non_scans(tmp_path: Path) -> None:
    for name, data, status in (
        ("upload", b"plain text, not an archive", 415),
        ("upload2", _zip({"a.png": _png(1)})[:40], 415),  # a cut zip, stored without a name: not an archive
        ("upload4", _png(7), 415),  # one 2-D image
        ("upload3", _zip({"readme.txt": b"hi"}), 422),
    ):
        path = _write(tmp_path, name, data)
        try:
            upload_check.inspect_upload(path, "scan.zip", JobParams(spacing=[1, 1, 1]))
        except UploadError as exc:
            assert exc.status == status, (name, exc.status, exc.detail)
            assert "scan.zip" in exc.detail
        else:
            raise AssertionError(f"{name}: accepted")


def test_the_worker_names_no_spacing_by_the_error_type() -> None:
    from worker.tasks import _explain

    code, message = _explain(NoSpacingError("upload: whatever the engine says"), "scan.zip")
    assert code == "no_spacing" and message.startswith("scan.zip: the image slices do not say how large a voxel is")
    code, message = _explain(InputError("upload: an image stack does not carry its voxel size"), "scan.zip")
    assert (code, message) == ("bad_input", "scan.zip: an image stack does not carry its voxel size")
    code, _ = _explain(NotAScanError("upload is not a readable zip archive"), "scan.zip")
    assert code == "bad_input"


def test_the_workers_source_errors_are_its_own_and_keep_their_codes() -> None:
    """The DICOMweb source's failures are the worker's (``JobSourceError``), not the engine's: no engine handler
    catches them, and ``_explain`` still names each by its type."""
    from engine.errors import EngineError
    from worker.pacs import JobSourceError, SourceIncomplete, SourceUnavailable, UncheckedSource
    from worker.tasks import _explain

    for cls in (SourceUnavailable, SourceIncomplete, UncheckedSource):
        assert issubclass(cls, JobSourceError) and not issubclass(cls, EngineError), cls.__mro__
    missing = ("1.2.3", "1.2.4", "1.2.5", "1.2.6")
    code, message = _explain(SourceIncomplete("pacs", 10, 6, missing), "scan.zip")
    assert code == "source_incomplete" and "6 of 10" in message and "1.2.3, 1.2.4, 1.2.5, ..." in message
    assert _explain(SourceUnavailable("server 'pacs' is not configured"), "scan.zip") == (
        "source_unavailable",
        "server 'pacs' is not configured",
    )
    code, message = _explain(UncheckedSource("upload: the source series was not checked complete"), "scan.zip")
    assert (code, message) == ("incomplete_series", "scan.zip: the source series was not checked complete")
