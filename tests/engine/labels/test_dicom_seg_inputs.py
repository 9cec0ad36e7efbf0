"""DICOM SEG files other projects publish (tests/data/dicom_seg: pydicom-data's liver SEG in every encoding it
ships, highdicom's SEGs of pydicom's small CT series), read through every path the same way (issue 41):

* every encoding decodes to the same masks: RLE Lossless and Deflated Image Frame Compression of 1-bit frames
  (byte-aligned 512 x 512 and non-aligned 510 x 510 frames) against JPEG 2000 (pydicom's decoder), plus SEGs made
  here from them (frames packed as one bit stream across frame boundaries, an 8-bit FRACTIONAL SEG deflated); an
  unsupported or damaged encoding is an ``InputError`` naming the transfer syntax;
* a SEG zipped, tarred or in a folder with its CT is found by one detection and read on the CT's grid, the same
  for all three; a SEG file alone is read on its own grid (several segments too); an archive or folder holding the
  SEG without its CT is refused naming the missing series; a SEG loaded as a scan is refused naming it;
* the CLI: exit 0 with the model, exit 2 with one line for what it cannot read.
"""

from __future__ import annotations

import io
import json
import shutil
import tarfile
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pydicom
import pydicom.data
import pytest
from pydicom.encaps import encapsulate

from engine.errors import IncompleteSeriesError, InputError, MissingReferenceError
from engine.io import load_volume
from engine.labels.dicom_seg import DEFLATED_FRAMES, RLE_LOSSLESS, read_dicom_seg, read_seg_folder, seg_pixels
from engine.labels.uploads import find_label_upload, read_label_upload
from tests.engine.labels.test_labels_util import highdicom_seg

DATA = Path(__file__).resolve().parents[2] / "data" / "dicom_seg"
CT2 = Path(pydicom.data.__file__).parent / "test_files" / "dicomdirtests" / "77654033" / "CT2"
CT2_SERIES = "1.3.6.1.4.1.5962.1.1.0.0.0.1196530851.28319.0.2"
CONTIGUOUS = ("17136", "17166", "17196")  # CT2's three slices 1.25 mm apart (its first lies 202.5 mm away)
needs_ct2 = pytest.mark.skipif(not CT2.is_dir(), reason="pydicom's test series dicomdirtests/77654033/CT2 is absent")


def _read(name: str) -> np.ndarray:
    return read_dicom_seg(DATA / name).labels


# --- encodings ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("size", ["", "nonbyte_aligned_"])
@pytest.mark.parametrize("encoding", ["rle", "deflate"])
def test_every_liver_encoding_reads_as_jpeg2000(size: str, encoding: str) -> None:
    """RLE Lossless (1.2.840.10008.1.2.5) and Deflated Image Frame Compression (1.2.840.10008.1.2.8.1) of 1-bit
    frames give exactly the masks JPEG 2000 gives (decoded by pydicom / pylibjpeg), frame by frame."""
    want = seg_pixels(pydicom.dcmread(DATA / f"liver_{size}j2k.dcm"), "j2k")
    ds = pydicom.dcmread(DATA / f"liver_{size}{encoding}.dcm")
    assert str(ds.file_meta.TransferSyntaxUID) == {"rle": RLE_LOSSLESS, "deflate": DEFLATED_FRAMES}[encoding]
    got = seg_pixels(ds, encoding)
    rows = 510 if size else 512
    assert got.shape == want.shape == (3, rows, rows)
    assert int(want.sum()) == 107_098  # the liver's voxels, in all three frames
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(_read(f"liver_{size}{encoding}.dcm"), _read(f"liver_{size}j2k.dcm"))


def _packbits(data: bytes) -> bytes:
    """A PackBits encoder (repeat runs of 2-128 bytes, literal runs up to 128)."""
    out, i, n = bytearray(), 0, len(data)
    while i < n:
        j = i
        while j + 1 < n and data[j + 1] == data[i] and j - i < 127:
            j += 1
        if j > i:
            out += bytes([257 - (j - i + 1)]) + data[i : i + 1]
            i = j + 1
            continue
        k = i
        while k + 1 < n and k - i < 127 and data[k + 1] != data[k]:
            k += 1
        out += bytes([k - i]) + data[i : k + 1]
        i = k + 1
    return bytes(out)


def _rle_frame(data: bytes) -> bytes:
    segment = _packbits(data)
    header = np.zeros(16, dtype="<u4")
    header[0], header[1] = 1, 64
    frame = header.tobytes() + segment
    return frame + b"\x00" * (len(frame) % 2)


def _with_frames(src: Path, uid: str, frames: list[bytes], path: Path) -> Path:
    """``src`` with its pixel data replaced by ``frames`` encapsulated under transfer syntax ``uid`` (written as
    Explicit VR Little Endian under RLE's UID, then given ``uid``'s file meta: pydicom 3.0 does not write a transfer
    syntax it does not know, such as Deflated Image Frame Compression)."""
    from pydicom.filebase import DicomBytesIO
    from pydicom.filewriter import write_file_meta_info

    ds = pydicom.dcmread(src)
    ds.file_meta.TransferSyntaxUID = pydicom.uid.RLELossless
    ds.PixelData = encapsulate(frames)
    ds["PixelData"].VR = "OB"
    ds["PixelData"].is_undefined_length = True
    buf = io.BytesIO()
    ds.save_as(buf, implicit_vr=False, little_endian=True, enforce_file_format=True)
    data = buf.getvalue()
    meta_end = 132 + 12 + int.from_bytes(data[140:144], "little")  # (0002,0000) group length
    ds.file_meta.TransferSyntaxUID = pydicom.uid.UID(uid)
    meta = DicomBytesIO()
    write_file_meta_info(meta, ds.file_meta, enforce_standard=True)
    path.write_bytes(data[:128] + b"DICM" + meta.getvalue() + data[meta_end:])
    return path


def _bit_stream_frames(pixels: np.ndarray) -> list[bytes]:
    """1-bit frames packed as one bit stream (as native pixel data), cut into one piece per frame at bytes."""
    stream = np.packbits(pixels.reshape(-1).astype(np.uint8), bitorder="little").tobytes()
    n = len(pixels)
    return [stream[len(stream) * f // n : len(stream) * (f + 1) // n] for f in range(n)]


@pytest.mark.parametrize("uid", [RLE_LOSSLESS, DEFLATED_FRAMES])
def test_frames_packed_across_frame_boundaries(tmp_path: Path, uid: str) -> None:
    """A writer that packs 510 x 510 1-bit frames as one stream (frame 2 starting in the middle of a byte) and
    cuts it per frame: read as the stream it is, the same masks."""
    want = seg_pixels(pydicom.dcmread(DATA / "liver_nonbyte_aligned_j2k.dcm"), "j2k")
    pieces = _bit_stream_frames(want)
    assert min(len(p) for p in pieces) < -(-510 * 510 // 8)  # not each a whole frame from a byte boundary
    encode = _rle_frame if uid == RLE_LOSSLESS else (lambda b: zlib.compress(b, 9)[2:-4])  # raw Deflate
    path = _with_frames(DATA / "liver_nonbyte_aligned_j2k.dcm", uid, [encode(p) for p in pieces], tmp_path / "s.dcm")
    np.testing.assert_array_equal(seg_pixels(pydicom.dcmread(path), "made"), want)


def test_fractional_8_bit_deflated(tmp_path: Path) -> None:
    """An 8-bit FRACTIONAL SEG (highdicom's, true fractions 0/64/128 of 255) deflated frame by frame reads as the
    native one: the voxels at or above half of MaximumFractionalValue."""
    src = DATA / "seg_image_ct_true_fractional.dcm"
    native = pydicom.dcmread(src).pixel_array
    frames = [zlib.compress(f.tobytes(), 6)[2:-4] for f in native]
    path = _with_frames(src, DEFLATED_FRAMES, frames, tmp_path / "frac.dcm")
    np.testing.assert_array_equal(seg_pixels(pydicom.dcmread(path), "made"), native)
    got, want = read_dicom_seg(path).labels, read_dicom_seg(src).labels
    np.testing.assert_array_equal(got, want)
    assert int(got.sum()) == int((native >= 128).sum())  # 128/255 >= half, 64/255 is not


def test_unsupported_or_damaged_encodings_name_the_transfer_syntax(tmp_path: Path) -> None:
    src = DATA / "liver_nonbyte_aligned_j2k.dcm"
    jpeg = _with_frames(src, "1.2.840.10008.1.2.4.50", [b"\xff\xd8 not a jpeg \xff\xd9"] * 3, tmp_path / "j.dcm")
    with pytest.raises(InputError, match=r"transfer syntax JPEG Baseline.*\(1\.2\.840\.10008\.1\.2\.4\.50\)"):
        read_dicom_seg(jpeg)
    bad = _with_frames(src, DEFLATED_FRAMES, [b"not deflate"] * 3, tmp_path / "d.dcm")
    with pytest.raises(InputError, match=r"1\.2\.840\.10008\.1\.2\.8\.1.*not Deflate"):
        read_dicom_seg(bad)
    short = _with_frames(src, RLE_LOSSLESS, [_rle_frame(b"\x00" * 100)] * 3, tmp_path / "r.dcm")
    with pytest.raises(InputError, match="fewer than the 97538 that 3 frames of 510 x 510 1-bit pixels need"):
        read_dicom_seg(short)


# --- a SEG with its CT, or alone -----------------------------------------------------------------------------------


def _inputs(tmp_path: Path, seg: str, ct: tuple[str, ...] = CONTIGUOUS) -> dict[str, Path]:
    """The SEG with CT slices as a folder, a zip and a tar.gz (the CT under a sub-folder, as exported)."""
    folder = tmp_path / "folder"
    (folder / "ct").mkdir(parents=True)
    shutil.copy(DATA / seg, folder / "seg.dcm")
    for name in ct:
        shutil.copy(CT2 / name, folder / "ct" / name)
    zipped, tarred = tmp_path / "seg_ct.zip", tmp_path / "seg_ct.tar.gz"
    with zipfile.ZipFile(zipped, "w") as zf:
        for f in sorted(folder.rglob("*")):
            if f.is_file():
                zf.write(f, f.relative_to(folder).as_posix())
        zf.writestr("__MACOSX/._seg.dcm", b"\x00\x05\x16\x07" + b"\x00" * 200)  # junk the loader ignores
    with tarfile.open(tarred, "w:gz") as tf:
        tf.add(folder, arcname=".")
    return {"folder": folder, "zip": zipped, "tar": tarred}


@needs_ct2
@pytest.mark.parametrize("seg", ["seg_image_ct_binary.dcm", "seg_image_ct_binary_overlap.dcm"])
def test_a_seg_with_its_ct_is_read_the_same_from_a_folder_a_zip_and_a_tar(tmp_path: Path, seg: str) -> None:
    inputs = _inputs(tmp_path, seg)
    ct = load_volume(inputs["folder"] / "ct")
    want = read_dicom_seg(DATA / seg, reference=ct)
    assert want.labels.shape == ct.data.shape == (3, 16, 16)
    for kind, path in inputs.items():
        found = find_label_upload(path, path.name, force=True)
        assert found is not None and found.kind == "dicom-seg", kind
        got = read_label_upload(path, found, path.name)
        np.testing.assert_array_equal(got.labels, want.labels)
        assert [s.name for s in got.segments] == [s.name for s in want.segments]
        assert got.source["placed_by"] == "Per-frame Plane Position into the referenced CT's grid"
        assert got.source["reference"]["completeness"]["complete"], kind
        np.testing.assert_allclose(got.origin_mm, ct.origin_mm)


@needs_ct2
def test_a_seg_on_an_incomplete_ct_says_so(tmp_path: Path) -> None:
    """pydicom's CT2 has 161 slices missing between its first two: the SEG's CT is named incomplete, not absent."""
    path = _inputs(tmp_path, "seg_image_ct_binary.dcm", ct=(*CONTIGUOUS, "17106"))["zip"]
    found = find_label_upload(path, "seg_ct.zip")
    with pytest.raises(
        IncompleteSeriesError,
        match=rf"seg_ct\.zip: seg\.dcm: the CT series it was drawn on \({CT2_SERIES}\).*161 slice",
    ):
        read_label_upload(path, found, "seg_ct.zip")


def test_a_seg_alone_on_its_own_grid_and_in_an_archive_refused_naming_its_series(tmp_path: Path) -> None:
    """The two-segment SEG alone: on its own grid (both segments; frames at the same position are segments, not
    two acquisitions), its overlap counted; zipped or in a folder without its CT: refused naming the series."""
    seg = DATA / "seg_image_ct_binary_overlap.dcm"
    ds = pydicom.dcmread(seg)
    found = find_label_upload(seg, seg.name)
    assert found is not None and found.kind == "dicom-seg"
    lv = read_label_upload(seg, found, seg.name)
    assert [(s.value, s.name) for s in lv.segments] == [(1, "first segment"), (2, "second segment")]
    assert lv.source["placed_by"] == "Per-frame Plane Position on the SEG's own grid"
    px = ds.pixel_array.astype(bool)
    assert lv.source["overlap_voxels"] == int((px[:4] & px[4:]).sum())  # frames 0-3 segment 1, 4-7 segment 2
    assert int((lv.labels > 0).sum()) == int((px[:4] | px[4:]).sum())
    assert lv.labels.shape[0] == 165  # 202.5 mm + 2 steps of 1.25 mm: the slices between are empty
    folder = tmp_path / "alone"
    folder.mkdir()
    shutil.copy(seg, folder / "seg.dcm")
    with zipfile.ZipFile(tmp_path / "alone.zip", "w") as zf:
        zf.write(seg, "seg.dcm")
    for path in (folder, tmp_path / "alone.zip"):
        with pytest.raises(
            MissingReferenceError, match=rf"without the CT series it was drawn on \(series {CT2_SERIES}"
        ):
            find_label_upload(path, path.name)


@needs_ct2
def test_a_seg_with_another_series_names_the_one_missing(tmp_path: Path) -> None:
    other = tmp_path / "other"
    other.mkdir()
    shutil.copy(DATA / "seg_image_ct_binary.dcm", other / "seg.dcm")
    ct = pydicom.dcmread(CT2 / "17136")
    ct.SeriesInstanceUID = "1.2.3.4"
    ct.save_as(other / "ct.dcm")
    with pytest.raises(
        MissingReferenceError, match=rf"other: seg\.dcm: its referenced series {CT2_SERIES} .*not in other"
    ):
        read_seg_folder(other)


def test_a_seg_loaded_as_a_scan_is_refused_naming_it() -> None:
    with pytest.raises(InputError, match=rf"is a DICOM Segmentation \(SEG\) of series {CT2_SERIES}: a label map"):
        load_volume(DATA / "seg_image_ct_binary_overlap.dcm")


def test_not_dicom_is_one_clear_line(tmp_path: Path) -> None:
    path = tmp_path / "slice.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 64)
    with pytest.raises(InputError) as err:
        read_dicom_seg(path)
    assert "force" not in str(err.value) and "\n" not in str(err.value)


# --- the CLI -------------------------------------------------------------------------------------------------------


def _cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    from engine.cli import main

    code = main(["reconstruct", *args, "--device", "cpu", "--quiet"])
    return code, capsys.readouterr().err


def test_cli_reads_a_1_bit_rle_seg(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    code, err = _cli([str(DATA / "liver_nonbyte_aligned_rle.dcm"), "-o", str(out)], capsys)
    assert code == 0, err
    report = json.loads((out / "report.json").read_text())
    (row,) = report["labels"]
    assert row["name"] == "Liver" and row["voxels"] == 107_098 and row["watertight"]
    assert report["frame"]["placed_by"] == "Per-frame Plane Position on the SEG's own grid"


@pytest.mark.parametrize("case", ["jpeg", "pieces", "png-zip"])
def test_cli_refuses_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str) -> None:
    out = tmp_path / "out"
    if case == "jpeg":
        src = DATA / "liver_nonbyte_aligned_j2k.dcm"
        path = _with_frames(src, "1.2.840.10008.1.2.4.50", [b"\xff\xd8\xff\xd9"] * 3, tmp_path / "j.dcm")
        args, want = [str(path)], "1.2.840.10008.1.2.4.50"
    elif case == "pieces":
        args, want = [str(DATA / "seg_image_ct_binary.dcm"), "--pieces", "2"], "is a DICOM Segmentation (SEG)"
    else:
        path = tmp_path / "slices.zip"
        with zipfile.ZipFile(path, "w") as zf:
            for i in range(3):
                zf.writestr(f"s{i}.png", b"\x89PNG\r\n\x1a\n" + bytes(64))
        args, want = [str(path), "--labels"], "holds no label map"
    code, err = _cli([*args, "-o", str(out)], capsys)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, err
    assert len(lines) == 1 and want in lines[0], err
    assert "internal error" not in err and "Traceback" not in err and "force=True" not in err
    assert not out.exists()


def test_a_nifti_jobs_report_says_what_placed_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import nibabel as nib

    data = np.zeros((12, 12, 12), np.uint8)
    data[3:9, 3:9, 3:9] = 1
    path = tmp_path / "cube.nii.gz"
    nib.save(nib.Nifti1Image(data, np.diag([2.0, 2.0, 2.0, 1.0])), str(path))
    code, err = _cli([str(path), "-o", str(tmp_path / "out")], capsys)
    assert code == 0, err
    frame = json.loads((tmp_path / "out" / "report.json").read_text())["frame"]
    assert frame["placed_by"] == "NIfTI sform (aligned space; RAS, turned into LPS)"  # nibabel sets sform code 2


def test_a_zip_member_copy_is_not_kept(tmp_path: Path) -> None:
    """A NIfTI in a zip is read from a temporary copy, gone afterwards (and the zip's other members ignored)."""
    import nibabel as nib

    img = nib.Nifti1Image(np.pad(np.ones((4, 4, 4), np.uint8), 2), np.eye(4))
    with zipfile.ZipFile(tmp_path / "map.zip", "w") as zf:
        zf.writestr("sub/labels.nii", img.to_bytes())
        zf.writestr("notes.txt", "x")
    found = find_label_upload(tmp_path / "map.zip")
    assert found is not None and (found.kind, found.member) == ("nifti", "sub/labels.nii")
    lv = read_label_upload(tmp_path / "map.zip", found)
    assert int(lv.labels.sum()) == 64 and lv.source["file"] == "sub/labels.nii"


def _raw(path: Path) -> bytes:
    """The file's data set without preamble and file meta (implicit VR little endian), as some exports hold."""
    from pydicom.filebase import DicomBytesIO
    from pydicom.filewriter import write_dataset

    ds = pydicom.dcmread(path)
    buf = DicomBytesIO()
    buf.is_little_endian, buf.is_implicit_VR = True, True
    write_dataset(buf, ds)
    return buf.getvalue()


@needs_ct2
def test_a_seg_without_file_meta_and_a_ct_that_only_references_a_seg(tmp_path: Path) -> None:
    """Detection reads the SOP class itself: a SEG data set without preamble and file meta (as the scan loader
    takes a CT without them) is a SEG; a CT whose header references a Segmentation is not one."""
    from engine.labels.uploads import is_seg

    raw = _raw(DATA / "seg_image_ct_binary.dcm")
    assert raw[:4] != b"DICM" and is_seg(raw[:4096])
    ct = pydicom.dcmread(CT2 / "17136")
    ct.ReferencedImageSequence = [pydicom.Dataset()]
    ct.ReferencedImageSequence[0].ReferencedSOPClassUID = "1.2.840.10008.5.1.4.1.1.66.4"
    ct.ReferencedImageSequence[0].ReferencedSOPInstanceUID = "1.2.3"
    buf = io.BytesIO()
    ct.save_as(buf)
    assert b"1.2.840.10008.5.1.4.1.1.66.4" in buf.getvalue()[:4096] and not is_seg(buf.getvalue()[:4096])
    path = tmp_path / "raw.zip"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("seg", raw)
        for name in CONTIGUOUS:
            zf.write(CT2 / name, f"ct/{name}")
    found = find_label_upload(path, "raw.zip")
    assert found is not None and found.kind == "dicom-seg"
    got = read_label_upload(path, found, "raw.zip")
    want = read_dicom_seg(DATA / "seg_image_ct_binary.dcm", reference=load_volume(path, series_uid=CT2_SERIES))
    np.testing.assert_array_equal(got.labels, want.labels)
    lone = tmp_path / "seg"
    lone.write_bytes(raw)
    np.testing.assert_array_equal(read_dicom_seg(lone).labels, read_dicom_seg(DATA / "seg_image_ct_binary.dcm").labels)


# --- dcmqi's 23 x 38 x 3 SEG (BrainLAB), frames of 874 bits --------------------------------------------------------

DCMQI = DATA / "dcmqi_23x38x3"


def test_dcmqi_seg_on_its_ct_is_dcmqis_label_map(tmp_path: Path) -> None:
    """dcmqi's SEG (23 columns x 38 rows: a frame is 109.25 bytes, so native frames run across byte boundaries) on
    its CT, from the folder and from a zip, and on its own grid: voxel for voxel and place for place the label map
    dcmqi converted it to (label.nrrd)."""
    from engine.labels.uploads import read_labels

    want = read_labels(DCMQI / "label.nrrd")
    folder = tmp_path / "up"
    shutil.copytree(DCMQI / "ct", folder / "ct")
    shutil.copy(DCMQI / "label.seg", folder / "label.seg")
    zipped = tmp_path / "up.zip"
    with zipfile.ZipFile(zipped, "w") as zf:
        for f in sorted(folder.rglob("*")):
            zf.write(f, f.relative_to(folder).as_posix())
    for path in (folder, zipped):
        found = find_label_upload(path, path.name, force=True)
        assert found is not None and found.kind == "dicom-seg"
        got = read_label_upload(path, found, path.name)
        np.testing.assert_array_equal(got.labels, want.labels)
        assert [s.name for s in got.segments] == ["Liver"] and int(got.labels.sum()) == 322
        for v in [(0, 0, 0), (2, 37, 22), (1, 20, 11)]:
            np.testing.assert_allclose(got.position(v), want.position(v), atol=1e-4)
    own = read_dicom_seg(DCMQI / "label.seg")
    np.testing.assert_array_equal(own.labels, want.labels)
    np.testing.assert_allclose(own.position((2, 37, 22)), want.position((2, 37, 22)), atol=1e-4)


@pytest.mark.parametrize("uid", [RLE_LOSSLESS, DEFLATED_FRAMES])
@pytest.mark.parametrize("packing", ["per-frame", "stream"])
def test_dcmqi_seg_reencoded(tmp_path: Path, uid: str, packing: str) -> None:
    """The same SEG with its 874-bit frames RLE- or Deflate-encoded, each from a byte boundary (PS3.5) or cut from
    one bit stream: the same masks."""
    ds = pydicom.dcmread(DCMQI / "label.seg")
    native = seg_pixels(ds, "native")
    assert native.shape == (3, 38, 23) and (38 * 23) % 8 != 0
    if packing == "per-frame":
        pieces = [np.packbits(f.reshape(-1), bitorder="little").tobytes() for f in native]
    else:
        pieces = _bit_stream_frames(native)
    encode = _rle_frame if uid == RLE_LOSSLESS else (lambda b: zlib.compress(b, 9)[2:-4])
    path = _with_frames(DCMQI / "label.seg", uid, [encode(p) for p in pieces], tmp_path / "seg.dcm")
    np.testing.assert_array_equal(seg_pixels(pydicom.dcmread(path), "made"), native)
    np.testing.assert_array_equal(read_dicom_seg(path).labels, read_dicom_seg(DCMQI / "label.seg").labels)


@needs_ct2
def test_a_label_map_seg_in_every_encoding(tmp_path: Path) -> None:
    """A LABELMAP SEG (Label Map Segmentation Storage, 8-bit values) written by highdicom on pydicom's CT slices,
    native and RLE (highdicom's encoders) and Deflated Image Frame Compression (here): the same label map, on the
    CT's grid and on its own."""

    sources = [pydicom.dcmread(CT2 / name) for name in CONTIGUOUS]
    labels = np.zeros((3, 16, 16), np.uint8)
    labels[0, 2:9, 3:12], labels[1, 5:14, 1:7], labels[2, 8:15, 8:15] = 1, 2, 3
    segments = [(n, f"part {n}", None) for n in (1, 2, 3)]
    paths = {}
    for name, uid in (("native", pydicom.uid.ExplicitVRLittleEndian), ("rle", pydicom.uid.RLELossless)):
        seg = highdicom_seg(sources, labels, segments, kind="LABELMAP", series_number=9, transfer_syntax_uid=uid)
        paths[name] = tmp_path / f"{name}.dcm"
        seg.save_as(paths[name])
    native = seg_pixels(pydicom.dcmread(paths["native"]), "native")
    assert native.dtype.itemsize == 1
    frames = [zlib.compress(f.tobytes(), 6)[2:-4] for f in native]
    paths["deflate"] = _with_frames(paths["native"], DEFLATED_FRAMES, frames, tmp_path / "deflate.dcm")
    folder = tmp_path / "ct"
    folder.mkdir()
    for name in CONTIGUOUS:
        shutil.copy(CT2 / name, folder / name)
    ct = load_volume(folder)
    for name, path in paths.items():
        on_ct = read_dicom_seg(path, reference=ct)
        np.testing.assert_array_equal(on_ct.labels, labels, err_msg=name)
        assert [s.name for s in on_ct.segments] == ["part 1", "part 2", "part 3"]
        np.testing.assert_array_equal(read_dicom_seg(path).labels, labels, err_msg=name)


def test_a_seg_alone_without_its_geometry_names_the_series_it_needs(tmp_path: Path) -> None:
    ds = pydicom.dcmread(DATA / "seg_image_ct_binary_overlap.dcm")
    for item in ds.PerFrameFunctionalGroupsSequence:
        del item.PlanePositionSequence
    ds.save_as(tmp_path / "seg.dcm")
    with pytest.raises(InputError, match=rf"no PlanePositionSequence .* without the referenced series {CT2_SERIES}"):
        read_dicom_seg(tmp_path / "seg.dcm")
