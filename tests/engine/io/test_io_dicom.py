"""engine.io.load_volume on DICOM series: synthetic (pydicom-written) and the real ones in ../shared/data."""

from __future__ import annotations

import json
import random
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from pydicom.uid import JPEG2000Lossless, RLELossless

from engine.errors import IncompleteSeriesError, InputError
from engine.io import load_volume
from tests.conftest import shared_file
from tests.engine.dicom_factory import PATIENT, ct_slice, dicomdir_like, series


def _zip(path: Path, files: dict[str, bytes], *, shuffle: bool = True) -> Path:
    names = list(files)
    if shuffle:
        random.Random(7).shuffle(names)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for n in names:
            zf.writestr(f"DICOM/{n}", files[n])
    return path


def _folder(path: Path, files: dict[str, bytes]) -> Path:
    path.mkdir()
    for n, data in files.items():
        (path / n).write_bytes(data)
    return path


def _ramp(p: np.ndarray) -> np.ndarray:
    """A linear HU field: linear interpolation reproduces it exactly (up to rounding)."""
    return 3.0 * p[..., 0] - 2.0 * p[..., 1] + 10.0 * p[..., 2]


def _patient_points(vol, shape: tuple[int, ...]) -> np.ndarray:
    """Patient coordinates (z, y, x, 3) of every voxel of ``vol``."""
    zz, yy, xx = np.indices(shape, dtype=float)
    sz, sy, sx = vol.spacing_zyx_mm
    axes = np.asarray(vol.direction)  # columns: x, y, z axes
    return (
        np.asarray(vol.origin_mm)
        + (xx[..., None] * sx) * axes[:, 0]
        + (yy[..., None] * sy) * axes[:, 1]
        + (zz[..., None] * sz) * axes[:, 2]
    )


@pytest.mark.parametrize("preamble", [True, False])
def test_shuffled_series_without_extensions_in_hu(tmp_path: Path, preamble: bool) -> None:
    files = series(_ramp, positions_mm=[0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20], preamble=preamble)
    files["DICOMDIR"] = dicomdir_like()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # one series, a skipped DICOMDIR: nothing to warn about
        vol = load_volume(_zip(tmp_path / "s.zip", files))
    assert vol.data.shape == (11, 24, 20)
    assert vol.data.dtype == np.int16 and vol.units == "HU"
    assert vol.spacing_zyx_mm == pytest.approx((2.0, 0.5, 0.5))
    assert vol.origin_mm == pytest.approx((-5.0, -6.0, 0.0))
    expected = _ramp(_patient_points(vol, vol.data.shape))
    assert np.abs(vol.data - expected).max() <= 0.5 + 1e-6
    assert vol.source["files"] == 11 and vol.source["other_files_skipped"] == 1
    assert vol.source["modality"] == "CT" and vol.source["resampled"] is False
    text = json.dumps(vol.source)
    for value in PATIENT.values():
        assert value not in text


def test_folder_and_float_rescale(tmp_path: Path) -> None:
    files = series(lambda p: 100 + 0 * p[..., 0], positions_mm=[0, 1, 2], slope=0.5, intercept=-1000.0)
    vol = load_volume(_folder(tmp_path / "dcm", files))
    assert vol.data.dtype == np.float32
    assert np.allclose(vol.data, 0.5 * 1124 - 1000)
    assert vol.source["container"] == "folder"


def test_non_ct_keeps_raw_units_and_dtype(tmp_path: Path) -> None:
    files = series(lambda p: 0 * p[..., 0], positions_mm=[0, 1, 2], modality="MR", intercept=0.0)
    vol = load_volume(_zip(tmp_path / "mr.zip", files))
    assert vol.units == "raw" and vol.data.dtype == np.uint16 and int(vol.data.max()) == 1024


def test_two_series_pick_largest_or_named(tmp_path: Path) -> None:
    big = series(_ramp, positions_mm=range(6), series_uid="1.2.3.4.1", name="A")
    small = series(_ramp, positions_mm=range(3), series_uid="1.2.3.4.2", name="B")
    path = _zip(tmp_path / "two.zip", {**big, **small})
    with pytest.warns(UserWarning, match=r"2 DICOM series.*1\.2\.3\.4\.1 \(6 images\)"):
        assert load_volume(path).data.shape[0] == 6
    assert load_volume(path, series_uid="1.2.3.4.2").data.shape[0] == 3
    with pytest.raises(InputError, match=r"no series '9\.9'.*1\.2\.3\.4\.1 \(6 images\); 1\.2\.3\.4\.2 \(3 images\)"):
        load_volume(path, series_uid="9.9")


def test_uneven_gaps_are_resampled(tmp_path: Path) -> None:
    positions = [0, 1, 2, 3, 5.5, 6.5, 7.5, 8.5]
    vol = load_volume(_zip(tmp_path / "gaps.zip", series(_ramp, positions_mm=positions)))
    assert vol.source["resampled"] is True
    assert vol.source["original_gaps_mm"] == [1, 1, 1, 2.5, 1, 1, 1]
    assert vol.spacing_zyx_mm[0] == pytest.approx(1.0)
    assert vol.data.shape == (9, 24, 20) and vol.data.dtype == np.int16
    expected = _ramp(_patient_points(vol, vol.data.shape))
    assert np.abs(vol.data - expected).max() <= 1.0


def test_gantry_tilt_is_shear_corrected(tmp_path: Path) -> None:
    """Slices tilted by 20 deg about x: each slice plane is oblique, and they step straight along patient z."""
    t = np.radians(20.0)
    iop = (1, 0, 0, 0, np.cos(t), -np.sin(t))
    normal = np.array([0.0, np.sin(t), np.cos(t)])
    step_z = 1.5  # IPP moves along patient z only, as on a tilted gantry
    ball_c = np.array([0.0, 0.0, 6.0])

    def field(p: np.ndarray) -> np.ndarray:
        return _ramp(p) + 400.0 * (np.linalg.norm(p - ball_c, axis=-1) < 3.0)

    # positions along the normal, plus in-plane drift so that the IPPs lie on the patient z axis
    positions = [k * step_z * normal[2] for k in range(10)]
    drift = np.array([0.0, 0.0, 1.0]) / normal[2] - normal
    files = series(field, positions_mm=positions, iop=iop, drift=drift, shape=(40, 30), tilt_deg=20.0)
    vol = load_volume(_folder(tmp_path / "tilt", files))
    assert vol.source["resampled"] is True
    assert vol.source["gantry_tilt_deg"] == pytest.approx(20.0, abs=0.01)
    assert np.allclose(np.asarray(vol.direction)[:, 2], normal, atol=1e-6)
    assert vol.data.shape[1] > 40  # the canvas grew to hold every shifted slice
    pts = _patient_points(vol, vol.data.shape)
    # the voxels that lie inside the acquired slab (in every slice's in-plane extent) match the analytic field
    inside = np.ones(vol.data.shape, bool)
    for d in (positions[0], positions[-1]):
        ipp = np.array([-5.0, -6.0, 0.0]) + d * normal + d * drift
        a = (pts - ipp) @ np.array([1.0, 0, 0]) / 0.5
        b = (pts - ipp) @ np.asarray(iop[3:]) / 0.5
        inside &= (a >= 0.5) & (a <= 28.5) & (b >= 0.5) & (b <= 38.5)
    assert inside.sum() > 0.4 * inside.size
    ramp_err = np.abs(vol.data - _ramp(pts))[inside & (np.linalg.norm(pts - ball_c, axis=-1) > 4.5)]
    assert ramp_err.max() <= 1.0
    ball = (vol.data - _ramp(pts)) > 200
    centre = pts[ball].mean(axis=0)
    assert np.allclose(centre, ball_c, atol=0.3)


def test_varying_orientation_is_refused(tmp_path: Path) -> None:
    files = series(_ramp, positions_mm=[0, 1, 2])
    files["IM9"] = ct_slice(
        np.zeros((24, 20), np.uint16),
        ipp=(0, 0, 3),
        iop=(1, 0, 0, 0, 0.9, -0.43589),
        series_uid=_uid(files),
        instance=9,
    )
    with pytest.raises(InputError, match="orientation changes within the series"):
        load_volume(_zip(tmp_path / "o.zip", files))


def _uid(files: dict[str, bytes]) -> str:
    import io

    import pydicom

    return str(pydicom.dcmread(io.BytesIO(next(iter(files.values())))).SeriesInstanceUID)


def test_duplicate_positions_identical_kept_once_different_refused(tmp_path: Path) -> None:
    files = series(_ramp, positions_mm=[0, 1, 1, 2, 3])  # IM2 and IM3: the same image at 1 mm, sent twice
    vol = load_volume(_zip(tmp_path / "dup.zip", files))
    assert vol.data.shape[0] == 4 and vol.source["resampled"] is False
    assert vol.source["completeness"]["duplicates_dropped"] == 1
    assert len(vol.instances) == 4 and len({i[1] for i in vol.instances}) == 4
    other = series(lambda p: _ramp(p) + 100.0, positions_mm=[1], series_uid=_uid(files), name="X")
    clash = {**series(_ramp, positions_mm=[0, 1, 2, 3], series_uid=_uid(files)), **other}
    with pytest.raises(IncompleteSeriesError, match=r"(IM2 and \S*X1|X1 and \S*IM2) lie at the same slice position but hold different"):
        load_volume(_zip(tmp_path / "clash.zip", clash))


def test_conflicting_spacing_is_refused(tmp_path: Path) -> None:
    path = _zip(tmp_path / "s.zip", series(_ramp, positions_mm=[0, 1, 2]))
    assert load_volume(path, spacing_zyx_mm=(1, 0.5, 0.5)).spacing_zyx_mm == pytest.approx((1, 0.5, 0.5))
    with pytest.raises(InputError, match="leave the spacing out"):
        load_volume(path, spacing_zyx_mm=(2, 0.5, 0.5))


@pytest.mark.parametrize("syntax", [RLELossless, JPEG2000Lossless], ids=["rle", "j2k"])
def test_compressed_transfer_syntaxes(tmp_path: Path, syntax: str) -> None:
    files = series(_ramp, positions_mm=[0, 1, 2, 3], shape=(40, 36), transfer_syntax=syntax)
    vol = load_volume(_zip(tmp_path / "c.zip", files))
    assert vol.source["transfer_syntax"] == syntax.name
    assert np.abs(vol.data - _ramp(_patient_points(vol, vol.data.shape))).max() <= 0.5 + 1e-6


# ---- real data in ../shared/data --------------------------------------------------------------------------------


def _meta(folder: str) -> dict:
    return json.loads(shared_file(folder, "meta.json").read_text())


@pytest.mark.parametrize("folder", ["head_phantom_dicom", "ctpace_phantom_dicom_nometa"])
def test_real_dicom_matches_its_png_twin(folder: str) -> None:
    meta = _meta(folder)
    vol = load_volume(shared_file(folder, meta["files"]["original_dicom"]))
    assert vol.data.shape == tuple(meta["shape_zyx"])
    assert vol.spacing_zyx_mm == pytest.approx(tuple(meta["spacing_mm_xyz"][::-1]), rel=1e-4)
    assert (int(vol.data.min()), int(vol.data.max())) == tuple(meta["hu_range"])
    assert vol.units == "HU" and vol.data.dtype == np.int16 and vol.source["resampled"] is False
    png = load_volume(shared_file(folder, meta["files"]["slices_png16"]), spacing_zyx_mm=vol.spacing_zyx_mm)
    assert np.array_equal(np.maximum(vol.data.astype(np.int32) + 1024, 0), png.data)
    for hu, count in meta["hu_count_above"].items():
        assert int((vol.data > int(hu)).sum()) == count


def test_real_gantry_tilt_is_resampled() -> None:
    meta = _meta("gantry_tilt_dicom")
    vol = load_volume(shared_file("gantry_tilt_dicom", meta["files"]["original_dicom"]))
    assert vol.source["resampled"] is True
    assert vol.source["gantry_tilt_deg"] == pytest.approx(18.5, abs=0.05)
    gaps = vol.source["original_gaps_mm"]
    assert len(gaps) == 27 and min(gaps) == pytest.approx(1.081, abs=0.01) and max(gaps) == pytest.approx(7.0, abs=0.01)
    sz, sy, sx = vol.spacing_zyx_mm
    assert (sy, sx) == pytest.approx(tuple(meta["spacing_mm_xyz"][1::-1]))
    assert sz == pytest.approx(4.002, abs=0.01)
    assert vol.data.shape[0] == int(sum(gaps) / sz + 1e-6) + 1 and vol.data.shape[2] == 512
    lo, hi = meta["hu_range"]
    assert lo <= int(vol.data.min()) and int(vol.data.max()) <= hi and int(vol.data.max()) > hi - 100
    # the first resampled plane is the first slice, shifted in-plane by a whole-and-fractional row offset
    png = load_volume(shared_file("gantry_tilt_dicom", meta["files"]["slices_png16"]), spacing_zyx_mm=(4, sy, sx))
    first = png.data[0].astype(np.float32)
    plane = np.maximum(vol.data[0].astype(np.float32) + 1024, 0)  # the PNG clipped the -1500 padding at 0
    off = vol.data.shape[1] - 512
    corr = max(np.corrcoef(plane[o : o + 512].ravel(), first.ravel())[0, 1] for o in (off - 1, off))
    assert corr > 0.99


def test_real_aapm_archive_fails_clearly() -> None:
    with pytest.raises(InputError, match="found none"):
        load_volume(shared_file("pelvis_ct", "pelvis_ct_original_aapm.zip"))


def test_no_positions_falls_back_to_instance_number(tmp_path: Path) -> None:
    import io

    import pydicom

    files = {}
    for name, data in series(lambda p: 10.0 * p[..., 2], positions_mm=[0, 1, 2, 3]).items():
        ds = pydicom.dcmread(io.BytesIO(data))
        del ds.ImagePositionPatient, ds.ImageOrientationPatient
        buf = io.BytesIO()
        ds.save_as(buf)
        files[name] = buf.getvalue()
    vol = load_volume(_zip(tmp_path / "np.zip", files))  # SliceThickness (1 mm) gives z
    assert vol.spacing_zyx_mm == pytest.approx((1.0, 0.5, 0.5))
    assert list(vol.data[:, 0, 0]) == [0, 10, 20, 30]
    single = tmp_path / "one.dcm"
    single.write_bytes(files["IM3"])
    with pytest.raises(IncompleteSeriesError, match=r"one\.dcm: the series has 1 image\(s\); a volume needs at least 3"):
        load_volume(single)
    del files["IM2"]  # instance numbers 1, 3, 4: one missing
    with pytest.raises(IncompleteSeriesError, match=r"numbered in steps of 1, but 1 are missing: instance 2"):
        load_volume(_zip(tmp_path / "hole.zip", files))
