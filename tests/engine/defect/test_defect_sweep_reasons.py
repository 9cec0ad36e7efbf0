"""The sweep's refusals measured on their own cuts (issue 42): a refusal carries its candidates, the sweep names the
one that held the cut (a refusal's message names the largest candidate, often the head's own asymmetry elsewhere)
or what the rules saw where none did, and a cut that crosses the scan's own plane is expected to be refused as a
midline defect. Small inputs; headsq is bundled."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.errors import NoDefectError
from engine.params import OrientParams
from engine.types import Volume


def _plane_at_x(volume: Volume, x_mm: float) -> SimpleNamespace:
    """The plane x = ``x_mm`` (grid mm) of ``volume``, its normal toward the patient's left."""
    from engine.defect.grid import Grid

    left = Grid.of(volume).left_in_grid()
    return SimpleNamespace(normal_grid=left, offset_grid_mm=float(left @ np.array([x_mm, 0.0, 0.0])))


def test_a_cut_across_the_plane_is_expected_to_be_a_midline_defect():
    """By the engine's own rule for a piece: bone removed on both sides of the plane by more than the largest voxel
    side crosses it; a cut on one side, or one that reaches past the plane by less than a voxel, does not."""
    from benchmarks.defect_quality import midline_crossing

    volume = Volume(np.zeros((6, 10, 40), dtype=np.int16), (2.0, 1.0, 1.0))
    plane = _plane_at_x(volume, 19.5)
    removed = np.zeros(volume.data.shape, dtype=bool)
    removed[2:4, 3:7, 22:30] = True
    one_side = midline_crossing(removed, volume, {"orient": None}, plane)
    assert not one_side["crosses_midline"] and one_side["removed_across_share"] == 0.0
    removed[2:4, 3:7, 19:22] = True  # 0.5 mm past the plane: under the largest voxel side (2 mm)
    assert not midline_crossing(removed, volume, {"orient": None}, plane)["crosses_midline"]
    removed[2:4, 3:7, 14:19] = True  # 5.5 mm past it
    across = midline_crossing(removed, volume, {"orient": None}, plane)
    assert across["crosses_midline"] and 0.2 < across["removed_across_share"] < 0.5
    lo, hi = across["removed_plane_mm"]
    assert lo < -2.0 < 2.0 < hi


def test_the_sweeps_refusal_reason_is_the_candidate_holding_the_cut():
    """Of a refusal's candidates, the one holding most of the removed bone is the cut's, with its verdict and how
    much of the cut it holds; the largest candidate (elsewhere) is not."""
    from benchmarks.defect_quality import cut_reason, cut_verdict

    volume = Volume(np.zeros((6, 10, 40), dtype=np.int16), (1.0, 1.0, 1.0))
    removed = np.zeros(volume.data.shape, dtype=bool)
    removed[2:4, 2:6, 30:34] = True  # 32 voxels
    elsewhere = np.argwhere(np.ones((4, 8, 8), dtype=bool)) + np.array([1, 1, 2])
    on_cut = np.argwhere(removed)[:24]
    exc = SimpleNamespace(candidates=[("moved bone: asymmetry", 500.0, elsewhere),
                                      ("smaller than the smallest defect (957 mm3)", 24.0, on_cut)])  # fmt: skip
    verdict = cut_verdict(exc, volume, {"orient": None}, removed)
    assert verdict["candidate"] == "the cut's" and verdict["reason"].startswith("smaller than")
    assert verdict["holds_removed"] == 0.75 and verdict["on_removed"] == 1.0
    assert cut_reason(verdict) == "the cut's candidate: smaller than the smallest defect"


def _symmetric_shell(hole: bool) -> tuple[Volume, np.ndarray]:
    """Two walls 6 voxels thick (1 mm voxels) mirrored across x = 19.5, and a round hole of radius 4 voxels through
    the left one where ``hole`` (else nothing removed): the scan and the removed voxels."""
    data = np.zeros((20, 30, 40), dtype=np.int16)
    data[:, :, 2:8] = 1000
    data[:, :, 32:38] = 1000
    z, y = np.indices(data.shape[:2])
    removed = np.zeros(data.shape, dtype=bool)
    if hole:
        disc = (z - 10) ** 2 + (y - 15) ** 2 < 4**2
        removed[disc, 32:38] = True
        data[removed] = 0
    return Volume(data, (1.0, 1.0, 1.0)), removed


def test_a_cut_no_candidate_holds_is_measured_where_it_is():
    """No candidate on the cut: the share of it whose mirror image is bone, its widest opening (the largest distance
    from a removed voxel to the bone) and the healthy shell at the mirror image; an opening narrower than that
    shell leaves no core. Where the mirror's bone is not the skull's piece (the largest), or the mirror lacks the
    bone, that is the reason."""
    from benchmarks.defect_quality import cut_verdict

    volume, removed = _symmetric_shell(hole=True)
    plane = _plane_at_x(volume, 19.5)
    exc = SimpleNamespace(candidates=[], shell_mm=6.0, plane_grid=(np.asarray(plane.normal_grid), plane.offset_grid_mm))
    verdict = cut_verdict(exc, volume, {"orient": None, "level": 500.0}, removed)
    assert verdict["candidate"] == "none on the cut" and verdict["mirror_bone_share"] == 1.0
    assert 3.0 <= verdict["opening_radius_mm"] <= 4.5 and verdict["mirror_shell_mm"] >= 5.0
    assert "narrower than twice the healthy shell" in verdict["reason"] and verdict["mirror_bone_in_skull"] == 1.0
    volume.data[:, :, 12:28] = 1000  # a larger piece apart from the walls: the skull, and the mirror's wall is not it
    volume.data[:, :, 11] = volume.data[:, :, 28] = 0
    verdict = cut_verdict(exc, volume, {"orient": None, "level": 500.0}, removed)
    assert verdict["mirror_bone_in_skull"] == 0.0 and "not the skull's piece" in verdict["reason"]
    volume.data[:, :, 12:28] = 0
    volume.data[:, :, 2:8] = 0  # the other side lacks the bone too
    verdict = cut_verdict(exc, volume, {"orient": None, "level": 500.0}, removed)
    assert verdict["mirror_bone_share"] == 0.0 and "mirror image lacks the bone" in verdict["reason"]


def test_the_overall_counts_keep_cuts_across_the_midline_apart():
    """A cut that crosses the midline is not a one-sided case: its refusal is counted apart, and every one-sided
    refusal is counted by its own cut's reason too."""
    from benchmarks.defect_quality import MIDLINE_EXPECTED, overall

    rows = [
        {"scan": "s", "diameter_mm": 20.0, "expected": "template, left", "outcome": "template", "dice": 0.8,
         "rim_gap_voxels": 0.2, "side": "left"},
        {"scan": "s", "diameter_mm": 20.0, "expected": "template, left",
         "outcome": "NoDefectError: no one-sided defect found: ...; the largest candidate (1 mm3) was left out: moved "
         "bone: the scan has bone beside it", "cut_verdict": {"candidate": "none on the cut",
                                                             "reason": "no candidate on the cut"}},
        {"scan": "s", "diameter_mm": 40.0, "expected": MIDLINE_EXPECTED,
         "outcome": "MidlineDefectError: the defect (1 mm3) the hole goes on past it toward the midline"},
        {"scan": "s", "diameter_mm": 40.0, "expected": MIDLINE_EXPECTED, "outcome": "template", "dice": 0.9,
         "rim_gap_voxels": 0.2, "side": "left", "past_plane_mm": 1.6},
        {"scan": "s", "diameter_mm": 30.0, "expected": "template, left", "outcome": "template", "dice": 0.8,
         "rim_gap_voxels": 0.2, "side": "left", "past_plane_mm": 0.7},
    ]  # fmt: skip
    out = overall(rows)
    assert out["cases"] == 3 and out["templates"] == 2 and out["refused"] == 1
    assert out["across_midline"] == {"cases": 2, "midline_refusals": 1, "other_refusals": 0, "templates": 1,
                                     "templates_with_a_midline_warning": 1}  # fmt: skip
    assert out["midline_warnings"] == 1  # the one-sided template whose hole reaches past the plane (under the bar)
    assert out["refused_by_reason"] == {"s 20 mm: NoDefectError: moved bone": 1}
    assert out["refused_by_cut_reason"] == {"s 20 mm: no candidate on the cut": 1}


@pytest.fixture(scope="module")
def headsq() -> Volume:
    from engine.io import load_volume

    return load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)


def test_a_refusal_carries_its_candidates(headsq, device):
    """The intact headsq is refused; the refusal carries every candidate's verdict, volume and voxels (whole grid),
    the skull's shell and the plane, for a caller that measures it (the sweep)."""
    from engine.defect import DefectParams, run

    with pytest.raises(NoDefectError) as info:
        run(headsq, DefectParams(), HEADSQ_LEVEL, device, orient=OrientParams(first_slice="superior"))
    exc = info.value
    cands = exc.candidates  # type: ignore[attr-defined]
    assert cands and all(isinstance(r, str) and r and v > 0 for r, v, _ in cands)
    assert all(i.ndim == 2 and i.shape[1] == 3 and (i >= 0).all() and (i < headsq.data.shape).all() for *_, i in cands)
    normal, _ = exc.plane_grid  # type: ignore[attr-defined]
    assert abs(float(np.linalg.norm(normal)) - 1.0) < 1e-6 and exc.shell_mm > 0  # type: ignore[attr-defined]
