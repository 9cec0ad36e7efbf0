"""Multi-frame DICOM (Enhanced CT, Legacy Converted Enhanced CT) through engine.io.load_volume: each must load as
the same volume as the single-frame series it was made from, whatever holds its macros, its frame order, its
files and its transfer syntax; and what cannot be placed is refused, naming the file and frame."""

from __future__ import annotations

import io
import random
import re
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest
from pydicom.uid import UID, JPEG2000Lossless, RLELossless, generate_uid

import engine.io.dicom_pixels as dicom_pixels
from engine.errors import InputError
from engine.io import inspect_input, load_volume
from engine.types import Volume
from tests.conftest import shared_file
from tests.engine.decode_spy import load_counting_pools
from tests.engine.dicom_factory import series
from tests.engine.multiframe_factory import enhanced_ct

POSITIONS = [0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0]


def _ramp(p: np.ndarray) -> np.ndarray:
    return 3.0 * p[..., 0] - 2.0 * p[..., 1] + 10.0 * p[..., 2]


def _zip(path: Path, files: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in files.items():
            zf.writestr(f"DICOM/{name}", data)
    return path


def _shuffled(n: int, seed: int = 3) -> list[int]:
    order = list(range(n))
    random.Random(seed).shuffle(order)
    assert order != sorted(order)
    return order


def _assert_same_volume(vol: Volume, ref: Volume) -> None:
    """The same voxels on the same grid in the same patient frame."""
    assert vol.data.shape == ref.data.shape and vol.data.dtype == ref.data.dtype
    np.testing.assert_array_equal(vol.data, ref.data)
    np.testing.assert_allclose(vol.spacing_zyx_mm, ref.spacing_zyx_mm, rtol=1e-9)
    np.testing.assert_allclose(vol.origin_mm, ref.origin_mm, atol=1e-6)
    np.testing.assert_allclose(vol.direction, ref.direction, atol=1e-9)
    assert (vol.units, vol.patient_frame) == (ref.units, ref.patient_frame)
    assert vol.source["resampled"] == ref.source["resampled"]


def _single_frame(tmp_path: Path, files: dict[str, bytes]) -> Volume:
    return load_volume(_zip(tmp_path / "single.zip", files))


# ---- synthetic Enhanced CT ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("shared", "legacy"),
    [
        (("PixelMeasuresSequence", "PlaneOrientationSequence", "PixelValueTransformationSequence"), False),
        ((), False),  # every macro per frame
        (("PixelMeasuresSequence",), True),  # a mix, in a Legacy Converted Enhanced CT
    ],
    ids=["shared", "per-frame", "mixed-legacy"],
)
def test_shuffled_frames_load_as_the_single_frame_series(tmp_path: Path, shared: tuple[str, ...], legacy: bool) -> None:
    files = series(_ramp, positions_mm=POSITIONS)
    ref = _single_frame(tmp_path, files)
    multi = enhanced_ct(list(files.values()), order=_shuffled(len(files)), shared=shared, legacy=legacy)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # one series, one file: nothing to warn about
        vol = load_volume(_zip(tmp_path / "multi.zip", {"ENH1": multi}))
    _assert_same_volume(vol, ref)
    assert vol.units == "HU" and vol.data.dtype == np.int16
    assert vol.spacing_zyx_mm == pytest.approx((2.0, 0.5, 0.5)) and vol.origin_mm == pytest.approx((-5.0, -6.0, 0.0))
    assert vol.source["series"]["used"]["images"] == len(POSITIONS)


def test_uneven_tilted_frames_get_the_same_geometry_checks_and_resampling(tmp_path: Path) -> None:
    """Uneven gaps and an in-plane drift (gantry tilt): resampled exactly as the single-frame series is."""
    files = series(_ramp, positions_mm=[0, 1, 2, 3, 4.5, 5.5, 6.5, 7.5], drift=(0.0, 0.3, 0.0), shape=(30, 26))
    ref = _single_frame(tmp_path, files)
    assert ref.source["resampled"] is True and ref.source["gantry_tilt_deg"] > 10
    vol = load_volume(_zip(tmp_path / "multi.zip", {"ENH1": enhanced_ct(list(files.values()), order=_shuffled(8))}))
    _assert_same_volume(vol, ref)
    assert vol.source["gantry_tilt_deg"] == ref.source["gantry_tilt_deg"]
    assert vol.source["original_gaps_mm"] == ref.source["original_gaps_mm"]


@pytest.mark.parametrize("syntax", [RLELossless, JPEG2000Lossless], ids=["rle", "j2k"])
def test_compressed_multiframe(tmp_path: Path, syntax: UID) -> None:
    files = series(_ramp, positions_mm=POSITIONS, shape=(40, 36))
    ref = _single_frame(tmp_path, files)
    multi = enhanced_ct(list(files.values()), order=_shuffled(len(files)), transfer_syntax=syntax)
    assert pydicom.dcmread(io.BytesIO(multi)).file_meta.TransferSyntaxUID == syntax
    vol = load_volume(_zip(tmp_path / "multi.zip", {"ENH1": multi}))
    _assert_same_volume(vol, ref)
    assert vol.source["transfer_syntax"] == syntax.name


@pytest.mark.parametrize(
    ("rescale", "dtype"),
    [
        ([(1.0, -1024.0 - 100.0 * (k % 3)) for k in range(len(POSITIONS))], np.int16),  # intercepts differ
        ([(0.5 if k % 2 else 1.0, -1024.0) for k in range(len(POSITIONS))], np.float32),  # slopes differ
    ],
    ids=["intercepts", "slopes"],
)
def test_each_frame_gets_its_own_rescale(tmp_path: Path, rescale: list[tuple[float, float]], dtype: type) -> None:
    files = series(_ramp, positions_mm=POSITIONS)
    ref = _single_frame(tmp_path, files)
    multi = enhanced_ct(
        list(files.values()), order=_shuffled(len(files)), rescale=rescale, shared=("PixelMeasuresSequence",)
    )
    stored = pydicom.dcmread(io.BytesIO(multi)).pixel_array
    assert len({int(frame[0, 0]) for frame in stored}) > 1 or dtype == np.float32  # really stored differently
    vol = load_volume(_zip(tmp_path / "multi.zip", {"ENH1": multi}))
    assert vol.data.dtype == dtype and vol.units == "HU"
    np.testing.assert_array_equal(vol.data, ref.data.astype(dtype))  # the same HU in every frame


def test_per_frame_macro_wins_over_the_shared_one(tmp_path: Path) -> None:
    files = series(_ramp, positions_mm=POSITIONS)
    ref = _single_frame(tmp_path, files)
    ds = pydicom.dcmread(io.BytesIO(enhanced_ct(list(files.values()), shared=("PlaneOrientationSequence",))))
    measures = pydicom.Dataset()
    measures.PixelSpacing = [9, 9]  # wrong, and overridden by every frame's own
    measures.SliceThickness = 9
    ds.SharedFunctionalGroupsSequence[0].PixelMeasuresSequence = pydicom.Sequence([measures])
    rescale = pydicom.Dataset()
    rescale.RescaleSlope, rescale.RescaleIntercept = 3, 5
    ds.SharedFunctionalGroupsSequence[0].PixelValueTransformationSequence = pydicom.Sequence([rescale])
    buf = io.BytesIO()
    ds.save_as(buf)
    _assert_same_volume(load_volume(_zip(tmp_path / "multi.zip", {"ENH1": buf.getvalue()})), ref)


@pytest.mark.parametrize("split", ["halves", "interleaved"])
def test_several_multiframe_files_of_one_series(tmp_path: Path, split: str) -> None:
    """Split stacks: the frames of two (or three) files make one series, whatever part of it each file holds."""
    files = series(_ramp, positions_mm=[float(z) for z in range(12)], shape=(40, 36))
    ref = _single_frame(tmp_path, files)
    images = list(files.values())
    parts = [images[:5], images[5:]] if split == "halves" else [images[0::3], images[1::3], images[2::3]]
    syntaxes = [RLELossless, JPEG2000Lossless, RLELossless]
    multi = {
        f"ENH{i + 1}": enhanced_ct(part, order=_shuffled(len(part), seed=i), transfer_syntax=syntaxes[i])
        for i, part in enumerate(parts)
    }
    path = _zip(tmp_path / "split.zip", multi)
    serial = load_volume(path, threads=1)
    _assert_same_volume(serial, ref)
    assert serial.source["series"]["used"]["images"] == 12
    _assert_same_volume(load_volume(path, threads=3, processes=False), ref)
    pools, in_procs = load_counting_pools(str(path))
    assert pools == [2]  # the files were decoded in 2 processes
    _assert_same_volume(in_procs, ref)


def test_a_file_is_parsed_and_decoded_once_not_once_per_frame(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    files = series(_ramp, positions_mm=[float(z) for z in range(40)], shape=(40, 36))
    path = _zip(tmp_path / "multi.zip", {"ENH1": enhanced_ct(list(files.values()), transfer_syntax=RLELossless)})
    from pydicom.pixels.decoders.base import Decoder

    parsed: list[str] = []
    walked: list[int] = []
    real_read, real_iter = dicom_pixels.read_dataset, Decoder.iter_array

    def read(member, *, pixels):  # type: ignore[no-untyped-def]
        parsed.append(member.name)
        return real_read(member, pixels=pixels)

    def iter_array(self, src, **kwargs):  # type: ignore[no-untyped-def]
        walked.append(1)
        return real_iter(self, src, **kwargs)

    monkeypatch.setattr(dicom_pixels, "read_dataset", read)
    monkeypatch.setattr(Decoder, "iter_array", iter_array)
    for threads in (1, 3):
        parsed.clear()
        walked.clear()
        vol = load_volume(path, threads=threads, processes=False)
        assert vol.data.shape == (40, 40, 36)
        assert parsed == ["DICOM/ENH1"]  # once for the pixels (the frames' headers came from the scan)
        assert walked == [1]  # its 40 frames decoded in one pass


def test_a_multiframe_file_alone_through_the_product(tmp_path: Path) -> None:
    files = series(_ramp, positions_mm=POSITIONS)
    ref = _single_frame(tmp_path, files)
    single = tmp_path / "enhanced.dcm"
    single.write_bytes(enhanced_ct(list(files.values()), order=_shuffled(len(files))))
    summary = inspect_input(single)
    assert (summary.kind, summary.files, summary.dicom) == ("file", 1, 1)
    vol = load_volume(single)
    _assert_same_volume(vol, ref)
    assert vol.source["container"] == "file"


# ---- refused, with the file and frame named ------------------------------------------------------------------------


def test_a_frame_without_plane_position_is_refused(tmp_path: Path) -> None:
    files = series(_ramp, positions_mm=POSITIONS)
    multi = enhanced_ct(list(files.values()), without_position=[2])
    with pytest.raises(InputError, match=r"multi\.zip: DICOM/ENH1 \[frame 3\] has no Plane Position \(Patient\)"):
        load_volume(_zip(tmp_path / "multi.zip", {"ENH1": multi}))


def test_a_frame_position_holding_nan_is_refused(tmp_path: Path) -> None:
    files = series(_ramp, positions_mm=POSITIONS)
    ds = pydicom.dcmread(io.BytesIO(enhanced_ct(list(files.values()))))
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pydicom warns of the invalid DS value it is told to write
        ds.PerFrameFunctionalGroupsSequence[1].PlanePositionSequence[0].ImagePositionPatient = ["NaN", "0", "2"]
        ds.save_as(buf)
    with pytest.raises(InputError, match=r"DICOM/ENH1 \[frame 2\] holds NaN or an infinity in ImagePositionPatient"):
        load_volume(_zip(tmp_path / "nan.zip", {"ENH1": buf.getvalue()}))


def test_a_broken_multiframe_file_of_another_series_does_not_stop_the_load(tmp_path: Path) -> None:
    files = series(_ramp, positions_mm=POSITIONS)
    other = series(_ramp, positions_mm=POSITIONS[:4], series_uid=generate_uid(), name="OTHER")
    broken = enhanced_ct(list(other.values()), without_position=[0])
    with pytest.warns(UserWarning, match="2 DICOM series"):
        vol = load_volume(_zip(tmp_path / "mixed.zip", {**files, "ENH1": broken}))
    assert vol.data.shape[0] == len(POSITIONS)


def test_multiframe_without_functional_groups_is_refused(tmp_path: Path) -> None:
    files = series(_ramp, positions_mm=POSITIONS[:3])
    ds = pydicom.dcmread(io.BytesIO(next(iter(files.values()))))
    frames = np.stack([pydicom.dcmread(io.BytesIO(f)).pixel_array for f in files.values()])
    ds.NumberOfFrames = 3
    ds.PixelData = frames.tobytes()
    buf = io.BytesIO()
    ds.save_as(buf)
    with pytest.raises(InputError, match=r"DICOM/MF is a multi-frame DICOM \(3 frames\) without functional groups"):
        load_volume(_zip(tmp_path / "mf.zip", {"MF": buf.getvalue()}))


def test_two_acquisitions_in_one_file_are_refused_naming_the_frames(tmp_path: Path) -> None:
    """Two temporal positions in one file (the same positions twice, different pixels): no single volume."""
    first = series(_ramp, positions_mm=POSITIONS)
    again = series(lambda p: _ramp(p) + 50.0, positions_mm=POSITIONS)
    multi = enhanced_ct([*first.values(), *again.values()])
    with pytest.raises(InputError, match="same slice position") as err:
        load_volume(_zip(tmp_path / "4d.zip", {"ENH1": multi}))
    frames = [int(n) for n in re.findall(r"DICOM/ENH1 \[frame (\d+)\]", str(err.value))]
    assert len(frames) == 2 and abs(frames[0] - frames[1]) == len(POSITIONS)  # a frame and its repeat


def _break_frame(data: bytes, index: int) -> bytes:
    """Make frame ``index`` (from 0) of an RLE multi-frame file undecodable: its header claims 9 segments."""
    out = bytearray(data)
    pos = out.find(b"\xe0\x7f\x10\x00") + 12  # Pixel Data: tag, VR OB, 2 reserved, undefined length
    for _ in range(index + 1):  # the Basic Offset Table item, then one fragment per frame
        assert out[pos : pos + 4] == b"\xfe\xff\x00\xe0"
        pos += 8 + int.from_bytes(out[pos + 4 : pos + 8], "little")
    out[pos + 8 : pos + 12] = (9).to_bytes(4, "little")
    return bytes(out)


def test_an_undecodable_frame_is_named_in_every_path(tmp_path: Path) -> None:
    files = series(_ramp, positions_mm=[float(z) for z in range(10)], shape=(40, 36))
    images = list(files.values())
    multi = {
        "ENH1": enhanced_ct(images[:5], transfer_syntax=RLELossless),
        "ENH2": _break_frame(enhanced_ct(images[5:], transfer_syntax=RLELossless), 3),
    }
    path = _zip(tmp_path / "broken.zip", multi)
    messages = []
    for threads, processes in ((1, False), (3, False), (2, True)):
        with pytest.raises(
            InputError, match=r"cannot decode the pixels of DICOM/ENH2 \[frame 4\] \(RLE Lossless\)"
        ) as err:
            load_volume(path, threads=threads, processes=processes)
        messages.append(str(err.value))
    assert len(set(messages)) == 1


# ---- the real head phantom (../shared/data) -------------------------------------------------------------------------


def _real_slices() -> tuple[Path, list[bytes]]:
    path = shared_file("head_phantom_dicom", "head_phantom_dicom.zip")
    with zipfile.ZipFile(path) as zf:
        images = [zf.read(n) for n in zf.namelist() if not n.endswith("DIRFILE")]
    assert len(images) == 28
    return path, images


@pytest.mark.parametrize("syntax", [None, JPEG2000Lossless], ids=["explicit-le", "j2k"])
def test_real_scan_as_enhanced_ct(tmp_path: Path, syntax: str | None) -> None:
    path, images = _real_slices()
    ref = load_volume(path)
    kwargs: dict[str, Any] = {} if syntax is None else {"transfer_syntax": syntax}
    multi = enhanced_ct(images, order=_shuffled(len(images)), shared=("PlaneOrientationSequence",), **kwargs)
    vol = load_volume(_zip(tmp_path / "enhanced.zip", {"ENH1": multi}))
    _assert_same_volume(vol, ref)
    assert vol.data.shape == (28, 512, 512) and vol.spacing_zyx_mm == pytest.approx((5.0, 0.451171875, 0.451171875))
    assert (int(vol.data.min()), int(vol.data.max())) == (-1024, 782)


def test_real_scan_as_legacy_converted_enhanced_ct_by_highdicom(tmp_path: Path) -> None:
    legacy = pytest.importorskip("highdicom.legacy", reason="highdicom (the test extra) is not installed")
    path, images = _real_slices()
    ref = load_volume(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # highdicom's notes about the source's optional attributes
        image = legacy.LegacyConvertedEnhancedCTImage(
            [pydicom.dcmread(io.BytesIO(b)) for b in images],
            series_instance_uid=generate_uid(),
            series_number=99,
            sop_instance_uid=generate_uid(),
            instance_number=1,
        )
        buf = io.BytesIO()
        image.save_as(buf)
    assert image.SOPClassUID == "1.2.840.10008.5.1.4.1.1.2.2" and int(image.NumberOfFrames) == 28
    single = tmp_path / "legacy.dcm"
    single.write_bytes(buf.getvalue())
    _assert_same_volume(load_volume(single), ref)
    _assert_same_volume(load_volume(_zip(tmp_path / "legacy.zip", {"LEGACY": buf.getvalue()})), ref)
