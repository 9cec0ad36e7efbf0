"""A series is whole before anything is reconstructed (engine.io.completeness): missing slices, clashing duplicates
and too few images are refused with the images named; genuinely uneven acquisitions are still resampled."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from engine.errors import IncompleteSeriesError, InputError
from engine.io import load_volume
from engine.io.completeness import check_numbering, check_positions
from tests.conftest import shared_file
from tests.engine.dicom_factory import series


def _zip(path: Path, files: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in reversed(list(files.items())):  # stored out of order: the positions give the order
            zf.writestr(name, data)
    return path


def _ramp(p: np.ndarray) -> np.ndarray:
    return 10.0 * p[..., 2] + 2.0 * p[..., 0]


# ---- the rules, on positions ----------------------------------------------------------------------------------------


def test_regular_positions_pass_and_say_so() -> None:
    found = check_positions(np.arange(10) * 1.25, [f"s{k}" for k in range(10)], "x", thickness_mm=1.25)
    assert found.report() == {
        "checked": True,
        "complete": True,
        "images_used": 10,
        "layout": "regular",
        "slice_spacing_mm": 1.25,
    }


@pytest.mark.parametrize(
    ("removed", "missing"),
    [([4], 1), ([4, 5], 2), ([0 + 1], 1), ([8], 1)],
    ids=["one", "two-adjacent", "second", "second-last"],
)
def test_a_gap_of_whole_spacings_names_the_images_beside_it(removed: list[int], missing: int) -> None:
    d = np.delete(np.arange(10) * 0.8 + 3.0, removed)
    names = [f"s{k}" for k in range(10) if k not in removed]
    with pytest.raises(IncompleteSeriesError, match=rf"{missing} slice\(s\) missing between s{removed[0] - 1} and "):
        check_positions(d, names, "scan.zip")


def test_what_a_cut_short_fetch_leaves_is_refused() -> None:
    """3 of 122 images 1 mm apart: positions 0, 40, 118 mm."""
    with pytest.raises(IncompleteSeriesError, match="39 slice"):
        check_positions(np.array([0.0, 40.0, 118.0]), ["a", "b", "c"], "fetched", thickness_mm=1.0)
    with pytest.raises(IncompleteSeriesError, match="a volume needs at least 3"):
        check_positions(np.array([0.0, 40.0]), ["a", "b"], "fetched", thickness_mm=1.0)


def test_variable_increment_runs_and_transitions_are_accepted() -> None:
    d = np.concatenate([np.arange(6) * 1.25, 6.25 + 2.5 + np.arange(6) * 2.5])  # 1.25 mm run, then a 2.5 mm run
    found = check_positions(d, [f"s{k}" for k in range(len(d))], "x", thickness_mm=1.25)
    assert found.layout == "variable spacing"
    assert found.runs == [{"images": 6, "spacing_mm": 1.25}, {"images": 7, "spacing_mm": 2.5}]
    # the gantry-tilt series' layout: 13 gaps of 4 mm, one of 1.08, 13 of 7 mm
    gaps = [4.0019] * 13 + [1.0811] + [6.9986] * 13
    d = np.concatenate([[0.0], np.cumsum(gaps)])
    assert check_positions(d, [f"s{k}" for k in range(len(d))], "x", thickness_mm=4.0).layout == "variable spacing"
    # two stacks joined at an offset that is not a whole number of slices
    d = np.array([0, 1, 2, 3, 5.5, 6.5, 7.5, 8.5])
    assert check_positions(d, [f"s{k}" for k in range(len(d))], "x").layout == "variable spacing"


def test_numbered_stacks() -> None:
    names = [f"slice_{k:03d}.png" for k in range(20) if k not in (7, 12, 13)]
    with pytest.raises(IncompleteSeriesError, match=r"3 are missing: slice_007\.png, slice_012\.png, slice_013\.png"):
        check_numbering(names, "stack.zip")
    assert check_numbering([f"img{k}.png" for k in range(0, 40, 2)], "x").layout == "numbered stack"
    assert check_numbering(["top.png", "mid.png", "bottom.png"], "x").layout == "unnumbered stack"
    assert check_numbering(["a1.png", "b2.png", "c4.png"], "x").layout == "unnumbered stack"


# ---- through the loader ---------------------------------------------------------------------------------------------


def test_dicom_series_with_a_slice_removed_is_refused(tmp_path: Path) -> None:
    files = series(_ramp, positions_mm=[float(k) for k in range(8)])
    whole = load_volume(_zip(tmp_path / "whole.zip", files))
    assert whole.source["completeness"]["layout"] == "regular" and whole.source["completeness"]["images_used"] == 8
    assert whole.source["series_uid"] and len(whole.instances) == 8
    del files["IM5"]
    with pytest.raises(IncompleteSeriesError, match=r"1 slice\(s\) missing between IM4 and IM6 \(a gap of 2 mm"):
        load_volume(_zip(tmp_path / "holed.zip", files))


def test_dicom_variable_spacing_is_still_resampled(tmp_path: Path) -> None:
    positions = [0, 1, 2, 3, 4, 6, 8, 10, 12]  # 1 mm run, then a 2 mm run
    vol = load_volume(_zip(tmp_path / "v.zip", series(_ramp, positions_mm=positions)))
    assert vol.source["resampled"] is True and vol.spacing_zyx_mm[0] == pytest.approx(1.5)
    assert vol.source["completeness"]["layout"] == "variable spacing"
    assert vol.source["completeness"]["resampled"] is True


def test_png_stack_with_a_missing_number_is_refused(tmp_path: Path) -> None:
    from tests.service.conftest import slice_zip, sphere_volume

    vol = (sphere_volume((12, 16, 16)) * 1000).astype(np.uint16)
    data = slice_zip(vol)
    with zipfile.ZipFile(io.BytesIO(data)) as src, zipfile.ZipFile(tmp_path / "holed.zip", "w") as dst:
        for info in src.infolist():
            if not info.filename.endswith("slice_0005.png"):
                dst.writestr(info, src.read(info))
    with pytest.raises(IncompleteSeriesError, match=r"1 are missing: slices/slice_0005\.png"):
        load_volume(tmp_path / "holed.zip", spacing_zyx_mm=(1, 1, 1))
    (tmp_path / "whole.zip").write_bytes(data)
    whole = load_volume(tmp_path / "whole.zip", spacing_zyx_mm=(1, 1, 1))
    assert whole.source["completeness"] == {
        "checked": True,
        "complete": True,
        "images_used": 12,
        "layout": "numbered stack",
    }


def test_single_image_is_not_a_volume(tmp_path: Path) -> None:
    from tests.service.conftest import png_bytes

    (tmp_path / "one.png").write_bytes(png_bytes(np.zeros((8, 8), np.uint16)))
    with pytest.raises(InputError, match=r"one\.png: the series has 1 image\(s\); a volume needs at least 3 slices"):
        load_volume(tmp_path / "one.png", spacing_zyx_mm=(1, 1, 1))


def test_real_series_with_one_slice_removed_is_refused(tmp_path: Path) -> None:
    """The head phantom (28 images, 5 mm): drop one image from the middle of the original DICOM zip."""
    src = shared_file("head_phantom_dicom", "head_phantom_dicom.zip")
    whole = load_volume(src)
    assert whole.source["completeness"]["layout"] == "regular" and whole.source["completeness"]["images_used"] == 28
    with zipfile.ZipFile(src) as zin:
        import pydicom

        headers = {i.filename: pydicom.dcmread(io.BytesIO(zin.read(i)), force=True) for i in zin.infolist()}
        infos = [i for i in zin.infolist() if "ImagePositionPatient" in headers[i.filename]]
        by_z = sorted(infos, key=lambda i: float(headers[i.filename].ImagePositionPatient[2]))
        gone = by_z[14]
        with zipfile.ZipFile(tmp_path / "holed.zip", "w") as zout:
            for info in infos:
                if info.filename != gone.filename:
                    zout.writestr(info, zin.read(info))
    before, after = by_z[13].filename, by_z[15].filename
    with pytest.raises(IncompleteSeriesError, match=rf"1 slice\(s\) missing between {before} and {after}"):
        load_volume(tmp_path / "holed.zip")


def test_real_gantry_tilt_keeps_its_resampling_and_says_so() -> None:
    vol = load_volume(shared_file("gantry_tilt_dicom", "gantry_tilt_dicom.zip"))
    c = vol.source["completeness"]
    assert c["layout"] == "variable spacing with gantry tilt" and c["resampled"] is True
    assert c["images_used"] == 28 and [r["images"] for r in c["runs"]] == [14, 14]


# ---- what the report says of a DICOM source (no free text) ------------------------------------------------------------

PHI = {
    "SeriesDescription": "Knee of Jane Roe 1961",
    "StudyDescription": "Fracture after fall, Ward 7",
    "ProtocolName": "Roe trauma protocol",
    "InstitutionName": "St Example Hospital",
    "OperatorsName": "Tech^Alice",
    "PerformingPhysicianName": "Dr^Bob",
    "InstitutionalDepartmentName": "Radiology West",
}


def phi_series() -> dict[str, bytes]:
    """A small CT series whose free-text fields hold made-up patient-identifying text."""
    import pydicom

    out = {}
    for name, data in series(lambda p: np.where(np.linalg.norm(p - [0, 0, 4], axis=-1) < 4, 1000.0, -1000.0),
                             positions_mm=[float(k) for k in range(9)], shape=(20, 20), origin=(-5, -5, 0)).items():
        ds = pydicom.dcmread(io.BytesIO(data))
        for key, value in PHI.items():
            setattr(ds, key, value)
        buf = io.BytesIO()
        ds.save_as(buf)
        out[name] = buf.getvalue()
    return out


def test_free_text_stays_out_of_the_report_and_the_viewer_files(tmp_path: Path) -> None:
    from engine.job.outputs import write_outputs
    from engine.params import ReconParams
    from engine.job.pipeline import reconstruct

    vol = load_volume(_zip(tmp_path / "phi.zip", phi_series()))
    params = ReconParams.from_dict({"iso": {"preset": "bone"}, "body": None})
    recon = reconstruct(vol, params, device="cpu")
    paths = write_outputs(recon, tmp_path / "out", params, device="cpu")
    report = json.loads(paths["report.json"].read_text())
    assert report["input"]["source"]["series"]["used"]["images"] == 9
    assert report["input"]["source"]["completeness"]["images_used"] == 9
    words = ("Jane", "Roe", "Knee", "Ward 7", "Example", "Alice", "Bob", "Radiology", "Fracture")
    for name, path in paths.items():
        blob = path.read_bytes()
        for text in (*PHI.values(), *words):
            assert text.encode() not in blob, (name, text)


@pytest.mark.parametrize("processes", [False, True], ids=["threads", "processes"])
def test_identical_images_at_one_position_kept_once_in_every_decode_path(tmp_path: Path, processes: bool) -> None:
    files = series(_ramp, positions_mm=[0, 1, 2, 2, 3, 4])  # IM3 and IM4: the same pixels, two SOP instances
    vol = load_volume(_zip(tmp_path / "dup.zip", files), threads=2, processes=processes)
    assert vol.data.shape[0] == 5 and vol.source["completeness"]["duplicates_dropped"] == 1
