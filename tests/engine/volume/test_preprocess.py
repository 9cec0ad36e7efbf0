"""The paper's slice preprocessing: threshold, area opening, Canny (in that order), and the crop's origin."""

from __future__ import annotations

import numpy as np
import pytest

from engine.params import IsoParams, PreprocessParams, ReconParams
from engine.job.pipeline import reconstruct
from engine.types import Volume
from engine.volume.preprocess import crop_volume, preprocess_volume


def slab_with_speck() -> np.ndarray:
    """Per slice: a 12x12 bright square (value 200) and a 2x2 bright speck (value 200) on a dark background."""
    data = np.full((5, 32, 32), 10, np.uint16)
    data[:, 8:20, 8:20] = 200
    data[:, 25:27, 25:27] = 200
    return data


def test_area_opening_removes_small_bright_specks_only():
    vol = Volume(slab_with_speck(), (1.0, 1.0, 1.0))
    out = preprocess_volume(vol, PreprocessParams(area_opening_px=10)).data
    assert (out[:, 25:27, 25:27] == 10).all()  # the 4-pixel speck is gone (down to its surroundings)
    np.testing.assert_array_equal(out[:, 8:20, 8:20], 200)  # the 144-pixel square stays
    kept = preprocess_volume(vol, PreprocessParams(area_opening_px=4)).data
    assert (kept[:, 25:27, 25:27] == 200).all()  # area 4 is not below the threshold 4


def test_canny_turns_each_slice_into_its_edge_map():
    vol = Volume(slab_with_speck(), (1.0, 1.0, 1.0))
    out = preprocess_volume(vol, PreprocessParams(canny_sigma=1.0)).data
    assert set(np.unique(out)) == {10, 200}  # edges at the maximum, the rest at the minimum
    edges = out[2] == 200
    assert edges[8:20, 7:9].any() and edges[8:20, 19:21].any()  # the square's left and right borders
    assert not edges[12:16, 12:16].any()  # no edge inside the flat square
    assert not edges[0:4, 0:4].any()  # nor in the flat background


def test_area_opening_runs_before_canny():
    """In the documented order the speck never reaches Canny; Canny first would leave its outline behind."""
    vol = Volume(slab_with_speck(), (1.0, 1.0, 1.0))
    out = preprocess_volume(vol, PreprocessParams(canny_sigma=1.0, area_opening_px=10)).data
    assert not (out[2, 22:30, 22:30] == 200).any()  # no edges around the removed speck
    assert (out[2, 8:20, 7:9] == 200).any()  # the square's outline is there


def test_threshold_then_pipeline_uses_the_preprocessed_volume():
    data = slab_with_speck().astype(np.float32)
    data[:, 2:4, 2:30] = 50  # a faint stripe, below the threshold
    vol = Volume(data, (1.0, 1.0, 1.0))
    params = ReconParams(
        preprocess=PreprocessParams(threshold=100.0, area_opening_px=10), iso=IsoParams(iso=30.0),
        gaussian=None, decimate=None, smooth=None, islands=None,
    )  # fmt: skip
    recon = reconstruct(vol, params, device="cpu")
    assert recon.report["mesh"]["components"] == 1  # the square only: stripe thresholded away, speck opened away


def test_crop_moves_the_origin_along_the_volume_axes():
    d = ((0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0))  # rows of a matrix whose columns are the x, y, z axes
    vol = Volume(np.zeros((6, 6, 6), np.float32), (2.0, 1.0, 0.5), origin_mm=(5.0, 6.0, 7.0), direction=d)
    cropped = crop_volume(vol, ((2.0, 10.0), (1.0, 5.0), (1.0, 2.5)))
    offset_xyz = np.array([2 * 0.5, 1 * 1.0, 1 * 2.0])
    np.testing.assert_allclose(cropped.origin_mm, np.add((5.0, 6.0, 7.0), np.asarray(d) @ offset_xyz))


@pytest.mark.parametrize("bad", [{"canny_sigma": 0}, {"area_opening_px": 0}])
def test_bad_preprocessing_values_are_refused(bad):
    with pytest.raises(ValueError):
        PreprocessParams(**bad)
