"""The template's confidence and its rim (issue 42): a template whose mirror image does not match the bone around
it is refused with the measure and the reason; a rim gap is closed across to the bone; the sweep's side of a case is
its own template's. Small inputs; headsq is bundled."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.errors import NoDefectError
from engine.params import OrientParams
from engine.types import Volume

HEADSQ_ORIENT = OrientParams(first_slice="superior")
HEADSQ_CRANIUM = (4, 18)


@pytest.fixture(scope="module")
def headsq() -> Volume:
    from engine.io import load_volume

    return load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)


def _plate_with_hole(gap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A flat plate 4 voxels thick (1 mm voxels) with a round hole of radius 12, and a template plate in the hole
    that stops ``gap`` voxels short of the rim all round: (bone, template, the hole)."""
    shape = (12, 40, 40)
    z, y, x = np.indices(shape)
    r = np.hypot(y - 19.3, x - 19.6)  # off the half voxel: the rim's projection rounds to even there
    slab = (z >= 4) & (z < 8)
    hole = slab & (r < 12)
    bone = slab & ~hole
    template = slab & (r < 12 - gap)
    return bone, template, hole


def _region(bone: np.ndarray):
    from engine.defect.region import Region

    data = np.where(bone, 1000.0, 0.0).astype(np.float32)
    return Region(lo=np.zeros(3, dtype=np.int64), mask=np.zeros(bone.shape, dtype=bool), data=data,
                  mirrored=data.copy(), bone=bone, level=500.0, tissue=0.0, mid=250.0, shell_mm=4.0,
                  skull_mm3=float(bone.sum()), min_volume_mm3=1.0)  # fmt: skip


def _grid(shape: tuple[int, ...], spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)):
    from engine.defect.grid import Grid

    return Grid(tuple(shape), spacing, np.eye(3), np.zeros(3), "test")  # type: ignore[arg-type]


def _short_piece(bone: np.ndarray, template: np.ndarray, spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)):
    """The region of ``bone``, its grid, and ``template`` as a piece with its rim measured (reach 6 mm)."""
    from engine.defect.region import Piece
    from engine.defect.rim import rim_of

    region, grid = _region(bone), _grid(bone.shape, spacing)
    index = np.argwhere(template)
    piece = Piece(label=1, voxels=len(index), volume_mm3=float(len(index)), core_mm3=1.0, index=index)
    piece.rim = rim_of(index, bone, grid.spacing_zyx, np.zeros(len(index), dtype=bool), 6.0)
    return region, grid, piece


def test_a_rim_gap_is_closed_across_to_the_bone():
    """A template 2 voxels short of the rim all round: closed, it touches the bone (gap <= 1 voxel), and what it
    gained lies in the hole, never in the bone."""
    from engine.defect.region import _close_rim

    bone, template, hole = _plate_with_hole(gap=2)
    region, grid, piece = _short_piece(bone, template)
    assert piece.rim.gap_voxels > 1.0
    contact = piece.rim.contact
    _close_rim(piece, region, grid, 4.0, border_of=grid.shape, reach=6.0)
    assert piece.rim.gap_voxels <= 0.5
    assert piece.rim.contact > max(contact, 0.7)
    assert piece.bridged_mm3 > 0
    grown = np.zeros(bone.shape, dtype=bool)
    grown[tuple(piece.index.T)] = True
    assert not (grown & bone).any()
    assert (grown & ~template).sum() == pytest.approx(piece.bridged_mm3)
    assert (grown & hole).sum() > template.sum()


def test_a_gap_wider_than_half_the_shell_is_not_bridged():
    """A template 4 voxels short of the rim (a 4 mm shell): the gap is left as it is (no plate grown that far)."""
    from engine.defect.region import _close_rim

    bone, template, _ = _plate_with_hole(gap=4)
    region, grid, piece = _short_piece(bone, template)
    before = piece.rim.gap_voxels
    _close_rim(piece, region, grid, 4.0, border_of=grid.shape, reach=6.0)
    assert piece.rim.gap_voxels == pytest.approx(before, abs=0.5)
    assert piece.rim.gap_voxels > 1.0


def thick_slice_hole() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A wall 4 mm thick cut across by 5 mm slices (spacing 5, 1, 1 mm) with a round hole, and a template of the
    hole one slice short at the top: ``(wall, bone, template, missing)``, ``missing`` the hole's last slice."""
    shape, zc, yc = (14, 40, 40), 7, 19.6
    z, y, x = np.indices(shape)
    wall = (x >= 18) & (x < 22)
    hole = wall & (np.hypot((z - zc) * 5.0, y - yc) < 12.0)
    top = int(np.argwhere(hole)[:, 0].max())
    return wall, wall & ~hole, hole & (z < top), hole & (z == top)


def test_a_slice_the_mirror_stops_short_of_is_bridged_between_thick_slices():
    """A wall 4 mm thick cut across by 5 mm slices, its round hole's template one slice short at the top (as the
    head phantom's mirror was): the closing bridges that slice (a step along the coarse axis counts as the ball's
    radius at most) and takes nothing of the bone."""
    from engine.defect.region import _close_rim

    wall, bone, template, missing = thick_slice_hole()  # the hole's last slice missing from the template
    region, grid, piece = _short_piece(bone, template, spacing=(5.0, 1.0, 1.0))
    assert piece.rim.gap_voxels > 0.0
    _close_rim(piece, region, grid, 4.0, border_of=grid.shape, reach=6.0)
    grown = np.zeros(wall.shape, dtype=bool)
    grown[tuple(piece.index.T)] = True
    assert (grown & missing).sum() >= 0.5 * missing.sum()
    assert not (grown & bone).any()


def test_a_template_that_the_mirror_does_not_fit_is_refused_with_the_measure(headsq, device, monkeypatch):
    """The confidence rule's reason names the overlap it measured (here the bar is raised past any fit)."""
    from engine.defect import DefectParams, run
    from engine.defect import region as region_mod
    from engine.defect.synthetic import cut_at

    cut = cut_at(headsq, HEADSQ_LEVEL, 157.5, 0.8, 40.0, slices=HEADSQ_CRANIUM, orient=HEADSQ_ORIENT, edge="ball",
                 fill="air")  # fmt: skip
    res = run(cut.volume, DefectParams(), HEADSQ_LEVEL, device, orient=HEADSQ_ORIENT)
    assert max(p.fit * p.rim.contact for p in res.kept) >= region_mod.MIN_CONFIDENCE
    monkeypatch.setattr(region_mod, "MIN_CONFIDENCE", 1.01)
    with pytest.raises(NoDefectError, match=r"low confidence: around it the mirror image matches the scan's bone over"):
        run(cut.volume, DefectParams(), HEADSQ_LEVEL, device, orient=HEADSQ_ORIENT)


def test_the_sweeps_side_is_the_cases_own_template():
    """With the scan's own defect left out, the side is where the rest of the template lies (the patient's left is
    +x of the LPS frame; this stack's x runs to the patient's left)."""
    from benchmarks.defect_quality import _side_of
    from engine.defect.grid import Grid

    volume = Volume(np.zeros((4, 8, 20), dtype=np.int16), (1.0, 1.0, 1.0))
    grid = Grid.of(volume)
    left = grid.left_in_grid()
    plane = SimpleNamespace(normal_grid=left, offset_grid_mm=float(left @ np.array([9.5, 3.5, 1.5])))
    mask = np.zeros(volume.data.shape, dtype=bool)
    assert _side_of(mask, volume, {"orient": None}, plane) is None
    mask[:, :, 15:] = True
    on_plus = "left" if left[0] > 0 else "right"
    assert _side_of(mask, volume, {"orient": None}, plane) == on_plus
    mask[:] = False
    mask[:, :, :3] = True
    assert _side_of(mask, volume, {"orient": None}, plane) == ("right" if on_plus == "left" else "left")
