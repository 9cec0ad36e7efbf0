"""Held-out full-thickness defects (issue 42): round cuts anywhere off the midline through the skull's wall
(``engine.defect.synthetic.cut_at``: straight, bevelled or ball-shaped edges, filled with tissue or air), on turned
poses (``synthetic.posed``), are found and filled; a partial-thickness dent is refused. headsq is bundled; the head
phantom needs ../shared."""

from __future__ import annotations

import pytest

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.errors import NoDefectError
from engine.params import OrientParams
from engine.types import Volume
from tests.conftest import shared_file

HEADSQ_ORIENT = OrientParams(first_slice="superior")
HEADSQ_CRANIUM = (4, 18)


@pytest.fixture(scope="module")
def headsq() -> Volume:
    from engine.io import load_volume

    return load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)


def _found(volume: Volume, removed, level: float, orient: OrientParams, device: str, side: str) -> float:
    from engine.defect import DefectParams, run
    from engine.defect.synthetic import dice

    res = run(volume, DefectParams(), level, device, orient=orient)
    assert res.side == side
    assert res.rim()["gap_voxels"] <= 1.0
    assert res.mesh_stats["watertight"]
    return dice(res.full_mask(), removed)


@pytest.mark.parametrize(
    ("azimuth", "height", "diameter", "edge", "fill", "side"),
    [
        (67.5, 0.5, 24.0, "ball", "tissue", "left"),  # a bevelled (ball-shaped) edge: was refused as a "sliver"
        (247.5, 0.5, 30.0, "bevelled", "air", "right"),
        (337.5, 0.5, 30.0, "straight", "tissue", "right"),  # frontal, 18 mm off the midline: was a "sliver"
        (157.5, 0.8, 40.0, "ball", "air", "left"),
    ],
)
def test_a_held_out_full_thickness_cut_is_filled(headsq, device, azimuth, height, diameter, edge, fill, side):
    from engine.defect.synthetic import cut_at

    cut = cut_at(headsq, HEADSQ_LEVEL, azimuth, height, diameter, slices=HEADSQ_CRANIUM, orient=HEADSQ_ORIENT,
                 edge=edge, fill=fill)  # fmt: skip
    assert _found(cut.volume, cut.removed, HEADSQ_LEVEL, HEADSQ_ORIENT, device, side) >= 0.65


def test_a_partial_thickness_dent_is_refused(headsq, device):
    from engine.defect import DefectParams, run
    from engine.defect.synthetic import cut_at

    cut = cut_at(headsq, HEADSQ_LEVEL, 202.5, 0.5, 40.0, slices=HEADSQ_CRANIUM, orient=HEADSQ_ORIENT,
                 depth_share=0.5)  # fmt: skip
    assert cut.removed_mm3 > 1000
    with pytest.raises(NoDefectError, match="no one-sided defect"):
        run(cut.volume, DefectParams(), HEADSQ_LEVEL, device, orient=HEADSQ_ORIENT)


def test_a_turned_head_phantom_with_a_cut_on_the_right(device):
    """The issue's case: the head phantom turned 7 degrees, a 32 mm cut on the right."""
    from engine.defect.synthetic import cut_at, posed
    from engine.io import load_volume

    path = shared_file("head_phantom_dicom", "head_phantom_png16.zip")
    volume = load_volume(path, spacing_zyx_mm=(5.0, 0.451171875, 0.451171875))
    orient = OrientParams(first_slice="inferior")
    cut = cut_at(volume, 1324.0, 247.5, 0.5, 32.0, slices=(12, 27), orient=orient, edge="ball")
    turned = posed(cut.volume, 7.0, 0.0, orient=orient)
    removed = posed(cut.volume, 7.0, 0.0, orient=orient, mask=cut.removed)
    assert _found(turned, removed, 1324.0, orient, device, "right") >= 0.65


def test_spans_shell_tells_a_hole_from_a_dent():
    """A flat shell 6 voxels thick with a hole through it spans the shell; the same with the outer half only
    removed (a dent) does not."""
    import numpy as np

    from engine.defect.rim import spans_shell

    shape = (40, 40, 20)
    mirrored = np.zeros(shape, dtype=np.float32)
    mirrored[:, :, 7:13] = 100.0  # the mirror image: an intact shell
    z, y = np.indices(shape[:2])
    disc = (z - 20) ** 2 + (y - 20) ** 2 < 8**2
    hole = np.zeros(shape, dtype=bool)
    hole[disc, 7:13] = True
    bone = (mirrored >= 50) & ~hole
    span = spans_shell(np.argwhere(hole), bone, mirrored, 50.0, (1.0, 1.0, 1.0), 9.0)
    assert span.share > 0.8 and span.area_mm2 > 150
    dent = np.zeros(shape, dtype=bool)
    dent[disc, 10:13] = True
    bone = (mirrored >= 50) & ~dent
    span = spans_shell(np.argwhere(dent), bone, mirrored, 50.0, (1.0, 1.0, 1.0), 9.0)
    assert span.share < 0.1


def test_the_sweep_measures_every_place():
    """benchmarks.defect_quality's sweep: 8 directions x 3 heights on headsq, each with Dice and rim gap or why not."""
    from benchmarks.defect_quality import sweep, sweep_markdown

    rows = sweep("headsq", "cpu", [30.0], poses=((0.0, 0.0),), log=lambda _: None)
    assert len(rows) == 24 and {r["azimuth_deg"] for r in rows} == {22.5 + 45 * k for k in range(8)}
    assert {r["edge"] for r in rows} == {"straight", "bevelled", "ball"} and {r["fill"] for r in rows} == {
        "tissue",
        "air",
    }
    found = [r for r in rows if "dice" in r]
    assert len(found) >= 18 and all(r["side"] == r["expected"].split(", ")[1] for r in found)
    assert sum(r["dice"] for r in found) / len(found) >= 0.75
    assert all(r["outcome"] == "template" or "Error" in r["outcome"] for r in rows)
    assert "| headsq | 0, 0 | 24 |" in sweep_markdown(rows)


def test_spans_shell_median_column_tells_a_hole_from_a_shifted_face():
    """A piece that a shifted mirror leaves along one face of the shell (a real head's own asymmetry) spans the shell
    along its edge at most: on its median column the scan has most of the mirrored shell (``Span.missing`` under
    ``region.MIN_SPAN_MISSING``); a hole lacks all of it."""
    import numpy as np

    from engine.defect.region import MIN_SPAN_MISSING
    from engine.defect.rim import spans_shell

    shape = (40, 40, 20)
    mirrored = np.zeros(shape, dtype=np.float32)
    mirrored[:, :, 7:13] = 100.0
    z, y = np.indices(shape[:2])
    disc = (z - 20) ** 2 + (y - 20) ** 2 < 8**2
    bone = mirrored >= 50
    bone[disc] = False
    bone[disc, 9:15] = True  # the scan's shell there: 2 voxels outward of the mirror's
    piece = np.argwhere((mirrored >= 50) & ~bone)
    assert spans_shell(piece, bone, mirrored, 50.0, (1.0, 1.0, 1.0), 9.0).missing < MIN_SPAN_MISSING
    hole = np.zeros(shape, dtype=bool)
    hole[disc, 7:13] = True
    span = spans_shell(np.argwhere(hole), (mirrored >= 50) & ~hole, mirrored, 50.0, (1.0, 1.0, 1.0), 9.0)
    assert span.missing >= MIN_SPAN_MISSING


def test_a_cut_under_the_resolution_is_refused_saying_why(headsq, device):
    """headsq's 3.2 mm voxels and 6 mm shell: a 20 mm cut at the orbits' roofs has the scan's bone within the
    shell's thickness of every voxel; the refusal says so in the scan's measures."""
    from engine.defect import DefectParams, run
    from engine.defect.synthetic import cut_at

    cut = cut_at(headsq, HEADSQ_LEVEL, 22.5, 0.2, 20.0, slices=HEADSQ_CRANIUM, orient=HEADSQ_ORIENT)
    with pytest.raises(NoDefectError, match=r"narrower than about twice that \(\d+ mm"):
        run(cut.volume, DefectParams(), HEADSQ_LEVEL, device, orient=HEADSQ_ORIENT)


def test_every_candidate_left_out_says_the_measure_it_failed(headsq, device):
    """A candidate reported "smaller than the smallest defect" is smaller than it (until issue 42, pieces that were
    never looked at, six others having more core, were reported so whatever their size: the gantry-tilt head's
    20 mm cuts); every candidate large enough is mirrored locally and judged."""
    import re

    from engine.defect import DefectParams
    from engine.defect.grid import Grid, bone_and_skull
    from engine.defect.plane import find_symmetry_plane
    from engine.defect.region import find_region
    from engine.defect.synthetic import cut_at

    cut = cut_at(headsq, HEADSQ_LEVEL, 247.5, 0.5, 30.0, slices=HEADSQ_CRANIUM, orient=HEADSQ_ORIENT, edge="bevelled")
    bone, skull = bone_and_skull(cut.volume.data, HEADSQ_LEVEL)
    plane = find_symmetry_plane(cut.volume, HEADSQ_LEVEL, orient=HEADSQ_ORIENT, skull=skull)
    grid = Grid.of(cut.volume, HEADSQ_ORIENT)
    region = find_region(cut.volume.data, HEADSQ_LEVEL, plane, grid, bone, skull, DefectParams(), device)
    assert region.kept
    for p in region.pieces:
        m = re.match(r"smaller than the smallest defect \((\d+) mm3", p.reason)
        if m:
            assert p.volume_mm3 < float(m.group(1)) + 1
        assert not p.reason.startswith("not looked at")
