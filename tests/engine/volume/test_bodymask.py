"""Bone of the body only (engine.volume.bodymask), speck removal by default, and the real scans' holders/couch."""

from __future__ import annotations

import numpy as np
import pytest

from engine.errors import InputError, NoBoneInBodyError
from engine.io import load_volume
from engine.params import BodyMaskParams, IsoParams, ReconParams
from engine.job.pipeline import reconstruct
from engine.types import Volume
from engine.volume.bodymask import body_outline, isolate_bone
from tests.conftest import shared_file

SP = (1.0, 1.0, 1.0)


def patient_on_a_couch(couch: bool = True, holder: bool = True, skull: bool = True) -> np.ndarray:
    """HU: air, an elliptic body of soft tissue (40 HU) with a bone ring (a skull, 900 HU) inside, resting on a
    couch plate (600 HU) without an air gap, and a holder plate (1000 HU) in the air beside it."""
    z, y, x = np.indices((20, 64, 64), dtype=np.float32)
    vol = np.full(z.shape, -1000.0, np.float32)
    r = np.hypot((y - 30) / 22, (x - 32) / 18)
    vol[(r < 1) & (z > 1) & (z < 18)] = 40.0
    if skull:
        vol[(r > 0.55) & (r < 0.75) & (z > 3) & (z < 16)] = 900.0
    if couch:
        vol[:, 52:55, 4:60] = 600.0  # the body (y up to 52) rests on it
    if holder:
        vol[4:16, 20:40, 56:59] = 1000.0
    return vol


def test_couch_and_holder_are_removed_and_reported():
    vol = Volume(patient_on_a_couch(), SP, units="HU")
    out, info = isolate_bone(vol, 300.0, BodyMaskParams(), hu_offset=0.0)
    assert info["applied"] and info["pieces"] == 3 and info["pieces_removed"] == 2
    couch_holder = int((vol.data >= 300).sum()) - int((patient_on_a_couch(False, False) >= 300).sum())
    assert info["voxels_removed"] == couch_holder and info["volume_removed_mm3"] == pytest.approx(couch_holder)
    np.testing.assert_array_equal(out.data >= 300, patient_on_a_couch(False, False) >= 300)  # the skull is kept
    assert vol.data.max() == 1000.0  # the input is not modified


def test_hu_plus_offset_stacks_use_the_offset_and_raw_data_are_left_alone():
    stored = (patient_on_a_couch() + 1024).astype(np.uint16)
    vol = Volume(stored, SP)
    _out, info = isolate_bone(vol, 1324.0, BodyMaskParams(), hu_offset=1024.0)
    assert info["pieces_removed"] == 2 and info["outline_stored"] == 524.0
    same, skipped = isolate_bone(vol, 1324.0, BodyMaskParams(), hu_offset=None)
    assert same is vol and not skipped["applied"] and "not in HU" in skipped["reason"]


def test_no_bone_in_the_body_fails_with_that_reason():
    vol = Volume(patient_on_a_couch(skull=False), SP, units="HU")
    with pytest.raises(NoBoneInBodyError, match="no bone inside the body"):
        isolate_bone(vol, 300.0, BodyMaskParams(), hu_offset=0.0)
    assert issubclass(NoBoneInBodyError, InputError)
    params = ReconParams(decimate=None, smooth=None)
    with pytest.raises(NoBoneInBodyError, match="couch"):
        reconstruct(vol, params, device="cpu")
    recon = reconstruct(vol, ReconParams(decimate=None, smooth=None, body=None), device="cpu")  # switched off
    assert recon.report["mesh"]["components"] == 2 and "body_mask" not in recon.report


def test_pipeline_drops_couch_and_specks_by_default_and_each_step_switches_off():
    data = patient_on_a_couch()
    data[10, 5, 5] = 900.0  # a one-voxel speck in the air: outside the body, removed with the couch
    data[10, 30, 32] = 900.0  # a one-voxel speck inside the body: kept by the mask, dropped as a speck
    vol = Volume(data, SP, units="HU")
    base = ReconParams(decimate=None, smooth=None)
    recon = reconstruct(vol, base, device="cpu")
    rep = recon.report
    assert rep["body_mask"]["pieces_removed"] == 3 and rep["mesh"]["components"] == 1  # the ring (a tube) alone
    assert rep["islands"]["removed_pieces"] == 1 and rep["islands"]["min_volume_mm3"] == pytest.approx(4.0)
    no_specks = reconstruct(vol, ReconParams(decimate=None, smooth=None, islands=None), device="cpu").report
    assert no_specks["mesh"]["components"] == 2 and "islands" not in no_specks  # the ring and the inner speck
    nothing = reconstruct(vol, ReconParams(decimate=None, smooth=None, islands=None, body=None), device="cpu").report
    # + couch and holder (the speck in the air does not survive the Gaussian: 900 HU in one voxel among -1000)
    assert nothing["mesh"]["components"] == 4
    assert ReconParams.from_dict({"body": None, "islands": None}) == ReconParams(body=None, islands=None)


def with_thin_plate(data: np.ndarray) -> np.ndarray:
    """A 2-voxel holder plate (330 HU: plastic at the bone level) in the air beside the body, wrapped in a one-voxel
    partial-volume rim at soft-tissue values: the rim closes around the plate in every slice, as around the head-holder
    plates of the gantry-tilt series."""
    out = data.copy()
    out[4:16, 19:42, 3:7] = 0.0  # the rim
    out[4:16, 20:41, 4:6] = 330.0  # the plate
    return out


def test_a_thin_plate_in_its_own_partial_volume_rim_is_outside_the_body():
    """Hole filling put the plate inside an outline of its own rim, so the plate stayed in the model."""
    vol = Volume(with_thin_plate(patient_on_a_couch(couch=False, holder=False)), SP, units="HU")
    out, info = isolate_bone(vol, 300.0, BodyMaskParams(), hu_offset=0.0)
    assert info["pieces_removed"] == 1 and info["voxels_removed"] == 12 * 21 * 2
    np.testing.assert_array_equal(out.data >= 300, patient_on_a_couch(couch=False, holder=False) >= 300)


def test_thick_body_parts_stay_and_a_lone_thin_part_stays():
    """A finger beside the trunk (tissue 5 mm in radius round a bone) is body; so is a thin part that is all a slice
    holds (the thin-part rule needs a thicker part in the same slice)."""
    data = patient_on_a_couch(couch=False, holder=False)
    z, y, x = np.indices(data.shape)
    finger = np.hypot(y - 30, x - 57) < 5.5
    data[(z > 3) & (z < 16) & finger] = 40.0
    data[(z > 3) & (z < 16) & (np.hypot(y - 30, x - 57) < 2.5)] = 900.0
    out, info = isolate_bone(Volume(data, SP, units="HU"), 300.0, BodyMaskParams(), hu_offset=0.0)
    assert info["pieces_removed"] == 0 and out.data is data
    alone = np.full((6, 30, 30), -1000.0, np.float32)
    alone[1:5, 10:20, 13:17] = 0.0  # 4 voxels thick: thin, but the only part of its slices
    alone[1:5, 11:19, 14:16] = 900.0
    body = body_outline(alone, 300.0, -500.0, SP, 0.0)
    assert body[1:5, 11:19, 14:16].all()


def _outline_slice_by_slice(data, level, outline, pixel_mm, radius_mm=3.0):
    """The outline as scipy gives it one slice at a time (``binary_fill_holes``, a 2-D erosion and 2-D labels): the
    oracle that the chunked, in-plane 3-D calls must equal."""
    from scipy import ndimage as ndi

    cross = ndi.generate_binary_structure(2, 1)
    out = np.zeros(data.shape, bool)
    for z in range(data.shape[0]):
        body = ndi.binary_fill_holes((data[z] >= outline) & (data[z] < level))
        thick = ndi.binary_erosion(body, structure=cross, iterations=max(1, round(radius_mm / pixel_mm)))
        if thick.any():
            parts, n = ndi.label(body, structure=cross)
            keep = np.bincount(parts[thick], minlength=n + 1) > 0
            keep[0] = False
            body = keep[parts]
        out[z] = body
    return out


@pytest.mark.parametrize("chunk", [1, 3, 16])
def test_the_outline_in_chunks_is_scipys_slice_by_slice(monkeypatch, chunk):
    """Holes that reach the slice's edge (not filled) and holes that do not (filled), a slice of thin parts only, a
    thin plate beside the body, empty slices, chunks that split the slices unevenly: the same outline as scipy's
    own per-slice calls, on the bundled headsq (another project's scan) and on these cases."""
    import engine.volume.bodymask as bm
    from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
    from engine.io.stack import load_slice_zip

    monkeypatch.setattr(bm, "CHUNK_PLANES", chunk)
    data = with_thin_plate(patient_on_a_couch(couch=True, holder=True))
    data[5, :, 0:3] = 40.0  # tissue on the slice's edge: the background beside it reaches the edge elsewhere
    data[6, 10:20, 10:20] = 40.0  # a square ring: its hole is filled
    data[6, 13:17, 13:17] = -1000.0
    data[7, :, 30:33] = 40.0  # a band across the whole slice splits its background: both halves reach the edge
    data[0] = -1000.0
    data[19] = 40.0  # a slice full of tissue
    for vol, level, outline, pixel in (
        (data, 300.0, -500.0, 1.0),
        (load_slice_zip(HEADSQ_ZIP), 1150.0, 300.0, HEADSQ_SPACING_ZYX_MM[1]),
    ):
        spacing = (1.0, pixel, pixel)
        got = body_outline(vol, level, outline, spacing, 0.0)
        np.testing.assert_array_equal(got, _outline_slice_by_slice(vol, level, outline, pixel))
    assert got.any() and not got.all()


@pytest.mark.parametrize("chunk", [1, 2, 5, 64])
def test_bone_pieces_in_chunks_are_scipys_pieces(monkeypatch, chunk):
    """The pieces labelled chunk by chunk and joined across the chunks' borders are the pieces of one
    ``scipy.ndimage.label`` call over the volume (26-connected; numbered in another order): random specks and
    strands that touch the next slice only diagonally, and the bundled headsq."""
    import engine.volume.bodymask as bm
    from scipy import ndimage as ndi

    from engine.data import HEADSQ_LEVEL, HEADSQ_ZIP
    from engine.io.stack import load_slice_zip

    monkeypatch.setattr(bm, "CHUNK_PLANES", chunk)
    rng = np.random.default_rng(7)
    specks = (rng.random((23, 40, 37)) > 0.82).astype(np.float32)
    diagonal = np.zeros((12, 12, 12), np.float32)
    for i in range(12):
        diagonal[i, i, i] = diagonal[i, 11 - i, i] = 1.0  # two strands, corner to corner: one piece where they cross
    for data, level in ((specks, 0.5), (diagonal, 0.5), (load_slice_zip(HEADSQ_ZIP), HEADSQ_LEVEL)):
        got, n = bm.bone_pieces(data, level)
        ref, n_ref = ndi.label(data >= level, structure=np.ones((3, 3, 3), bool))
        assert n == n_ref and got.max() == n and np.array_equal(got > 0, ref > 0)
        pairs = np.unique(np.stack([got[ref > 0], ref[ref > 0]]), axis=1)
        assert pairs.shape[1] == n  # one to one: the same pieces


# ---- the real scans (../shared/data) -----------------------------------------------------------------------------
def test_cranium_print_model_has_no_holder_plates():
    vol = load_volume(shared_file("cranium_ct", "cranium_ct_png16.zip"), spacing_zyx_mm=(1.5, 0.9570312, 0.9570312))
    out, info = isolate_bone(vol, 1324.0, BodyMaskParams(), hu_offset=1024.0)
    # README: above 1324, the skull + mandible and "two 18.5k-voxel pieces = the head-holder arc (not bone)"
    assert info["pieces_removed"] == 2 and 36_000 < info["voxels_removed"] < 38_000
    kept = out.data >= 1324
    assert int(kept.sum()) > 400_000  # the skull (402,994 voxels in 6-connectivity) stays
    xs = np.flatnonzero(kept.any(axis=(0, 1)))
    assert (xs.max() - xs.min()) * 0.957 < 160  # no holder beside the skull: about a skull's width


def test_head_phantom_print_model_has_no_couch():
    vol = load_volume(shared_file("head_phantom_dicom", "head_phantom_dicom.zip"))
    out, info = isolate_bone(vol, 300.0, BodyMaskParams(), hu_offset=0.0)
    # README: "couch/head rest 55,436 voxels (not bone)" in 6-connectivity; 26-connected it is one piece
    assert info["voxels_removed"] >= 55_436 and info["volume_removed_mm3"] > 50_000
    assert int((out.data >= 300).sum()) > 274_170  # the phantom skull stays


def test_ctpace_has_no_bone_in_the_body():
    vol = load_volume(shared_file("ctpace_phantom_dicom_nometa", "ctpace_phantom_dicom.zip"))
    with pytest.raises(NoBoneInBodyError, match="no bone inside the body"):
        reconstruct(vol, ReconParams(iso=IsoParams(preset="bone")), device="cpu")


def test_gantry_tilt_series_has_no_head_holder_plates():
    """The two plates beside the skull (1,456 and 873 mm3 in the model, 18 mm outside it) survived the mask."""
    vol = load_volume(shared_file("gantry_tilt_dicom", "gantry_tilt_dicom.zip"))  # resampled: tilt, uneven gaps
    out, info = isolate_bone(vol, 300.0, BodyMaskParams(), hu_offset=0.0)
    kept = out.data >= 300
    xs = np.flatnonzero(kept.any(axis=(0, 1)))
    assert (xs.max() - xs.min() + 1) * vol.spacing_zyx_mm[2] < 160  # the skull's width (the plates made it 196)
    assert info["kept_mm3"] > 560_000 and info["pieces_removed"] >= 7
