"""A model per label (engine.labels): label maps made from the real headsq scan (bone halves either side of the
mid-sagittal plane, touching across it; tissue around the bone) meshed in one batch: each part watertight, placed in
the patient frame, disjoint from its neighbours, its volume close to its voxels'; the budget shared by area; the N
largest bone pieces of a CT; a region of interest."""

from __future__ import annotations

import numpy as np
import pytest

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM
from engine.errors import EmptyLabelError, EmptySurfaceError, InputError
from engine.io.labelmaps import LabelVolume, Segment
from engine.labels import bone_pieces, crop_roi, label_models, mesh_labels, share_by_area
from engine.params import DecimateParams, IsoParams, PiecesParams, ReconParams, RoiParams
from engine.types import Volume
from tests.conftest import shared_file
from tests.engine.labels.test_labels_util import assert_disjoint, headsq_data, headsq_labels, split_map

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def halves() -> tuple[LabelVolume, object]:
    """Bone halves and the tissue around them, in 24 slices of headsq (small and fast)."""
    lv = crop_roi(headsq_labels(soft=500.0), RoiParams(((30, 54), (0, 64), (0, 64))))
    return lv, label_models(lv, device="cpu")


@pytest.fixture(scope="module")
def bone_only() -> tuple[LabelVolume, object]:
    lv = headsq_labels()
    return lv, label_models(lv, device="cpu")


def test_every_part_is_watertight_named_and_coloured(halves) -> None:
    lv, models = halves
    assert [p.name for p in models.parts] == ["bone_right", "bone_left", "tissue"]
    for part, seg in zip(models.parts, lv.segments, strict=True):
        assert part.stats["watertight"], part.name
        assert part.color == seg.color and len(part.faces) == part.stats["faces"] > 100
    assert [r["file"] for r in models.report["labels"]] == [f"labels/{p.name}.stl" for p in models.parts]


def test_volumes_are_close_to_the_voxels(bone_only, halves) -> None:
    """Where labels touch little (the halves meet on the mid-sagittal plane only), each part's volume is its voxels'
    within 10 %; a thin bone wrapped in a tissue label retreats about 0.3 voxel on every side it shares (the price
    of disjoint meshes, docs/labels.md): the skull of headsq (2-3 voxels thick) keeps 60-90 %."""
    for part in bone_only[1].parts:
        assert part.stats["volume_mm3"] == pytest.approx(part.stats["voxel_volume_mm3"], rel=0.1), part.name
        assert part.stats["watertight"]
    for part in halves[1].parts:
        assert 0.6 < part.stats["volume_mm3"] / part.stats["voxel_volume_mm3"] < 1.0, part.name


def test_touching_labels_stay_apart(halves) -> None:
    """The two bone halves touch across the mid-sagittal plane and the tissue wraps the bone: no two parts share a
    vertex, cross or contain each other."""
    _, models = halves
    right, left, tissue = models.parts
    gap = assert_disjoint(
        right.vertices_xyz.astype(np.float64), right.faces, left.vertices_xyz.astype(np.float64), left.faces
    )
    assert gap < 2 * max(HEADSQ_SPACING_ZYX_MM)  # they do face each other across the plane
    for bone in (right, left):
        assert_disjoint(
            bone.vertices_xyz.astype(np.float64), bone.faces, tissue.vertices_xyz.astype(np.float64), tissue.faces
        )


def test_parts_lie_in_the_patient_frame(halves) -> None:
    """A part's vertices lie on its label's voxels placed by the map's (rotated) geometry."""
    lv, models = halves
    for part in models.parts:
        idx = np.round(lv.index_of(part.vertices_xyz)).astype(int)
        idx = np.clip(idx, 0, np.array(lv.labels.shape) - 1)
        near = np.zeros(len(idx), bool)
        for dz in (-1, 0, 1):  # a vertex lies within a voxel of its label's voxels
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    j = np.clip(idx + np.array([dz, dy, dx]), 0, np.array(lv.labels.shape) - 1)
                    near |= lv.labels[j[:, 0], j[:, 1], j[:, 2]] == part.value
        assert near.mean() > 0.99, part.name


def test_budget_is_shared_by_area() -> None:
    lv = headsq_labels()
    params = ReconParams(decimate=DecimateParams(reduction=None, max_triangles=6000))
    models = label_models(lv, params, device="cpu")
    info = models.report["labels_mesh"]["decimate"]
    share = np.array(info["share_faces"])
    areas = np.array([p.stats["area_mm2"] for p in models.parts])
    faces = np.array([p.stats["faces"] for p in models.parts])
    assert share.sum() <= 6000 + 2 and np.argmax(share) == np.argmax(areas)
    assert np.all(faces <= share * 1.05 + 4) or info["limited_by_guards"]
    assert all(p.stats["watertight"] for p in models.parts)


def test_share_by_area() -> None:
    np.testing.assert_array_equal(share_by_area(np.array([1.0, 3.0, 0.0]), 1000), [250, 750, 4])


def test_empty_label_is_refused() -> None:
    labels = np.zeros((8, 8, 8), np.uint8)
    labels[2:5, 2:5, 2:5] = 1
    with pytest.raises(EmptyLabelError, match=r"\[2\]"):
        mesh_labels(labels, [1, 2], (1.0, 1.0, 1.0), device="cpu")


def test_pieces_keep_the_largest_bone_pieces() -> None:
    data = headsq_data()
    vol = Volume(data, HEADSQ_SPACING_ZYX_MM)
    params = ReconParams(iso=IsoParams(iso=HEADSQ_LEVEL), body=None)
    lv = bone_pieces(vol, params, PiecesParams(count=3))
    sizes = lv.source["piece_voxels"]
    assert [s.name for s in lv.segments] == ["piece_1", "piece_2", "piece_3"] and sizes == sorted(sizes, reverse=True)
    assert [int((lv.labels == v).sum()) for v in (1, 2, 3)] == sizes
    models = label_models(lv, params, device="cpu")
    assert all(p.stats["watertight"] for p in models.parts)
    with pytest.raises(EmptySurfaceError):
        bone_pieces(vol, ReconParams(iso=IsoParams(iso=5000.0), body=None))


def test_real_ct_bone_halves_either_side() -> None:
    """The cranium CT (../shared/data): its bone split at the mid-sagittal plane, one part each side, apart."""
    from engine.io import load_volume

    vol = load_volume(shared_file("cranium_ct", "cranium_ct_png16.zip"), spacing_zyx_mm=(1.0, 0.49, 0.49))
    vol = crop_roi(vol, RoiParams(((0, 40), (0, vol.data.shape[1]), (0, vol.data.shape[2]))))
    vol.data = vol.data[:, ::4, ::4].copy()
    vol.spacing_zyx_mm = (1.0, 1.96, 1.96)
    labels = split_map(vol.data, 1024 + 300)
    lv = LabelVolume(
        labels, vol.spacing_zyx_mm, segments=(Segment(1, "right", (1, 0, 0)), Segment(2, "left", (0, 0, 1)))
    )
    models = label_models(lv, device="cpu")
    a, b = models.parts
    assert a.stats["watertight"] and b.stats["watertight"]
    assert_disjoint(a.vertices_xyz.astype(np.float64), a.faces, b.vertices_xyz.astype(np.float64), b.faces)
    assert a.vertices_xyz[:, 0].max() < b.vertices_xyz[:, 0].min() + 2.0  # one each side of the plane


def test_roi_keeps_every_voxel_in_place() -> None:
    lv = headsq_labels()
    cut = crop_roi(lv, RoiParams(((10, 60), (5, 50), (20, 64))))
    assert cut.labels.shape == (50, 45, 44)
    np.testing.assert_array_equal(cut.labels, lv.labels[10:60, 5:50, 20:64])
    np.testing.assert_allclose(cut.position((3, 4, 5)), lv.position((13, 9, 25)), atol=1e-9)
    # the same box in patient mm: its corners are voxel centres
    corners = np.array([lv.position((z, y, x)) for z in (10, 59) for y in (5, 49) for x in (20, 63)])
    box = tuple((float(lo), float(hi)) for lo, hi in zip(corners.min(0), corners.max(0), strict=True))
    in_mm = crop_roi(lv, RoiParams(box, units="mm"))
    assert in_mm.labels.shape[0] == 50
    np.testing.assert_allclose(
        in_mm.position((0, 0, 0)), lv.position(np.array(in_mm.source["roi"]["slices_zyx"])[:, 0])
    )


def test_roi_outside_the_scan_is_refused() -> None:
    lv = headsq_labels()
    with pytest.raises(InputError, match="region of interest"):
        crop_roi(lv, RoiParams(((200, 300), (0, 10), (0, 10))))
    with pytest.raises(ValueError, match="lo < hi"):
        RoiParams(((5, 5), (0, 10), (0, 10)))


def test_a_label_too_thin_for_a_surface_is_listed_not_written() -> None:
    """A one-voxel label peaks below 0.5 after the Gaussian: no part, named in ``labels_without_surface``."""
    labels = np.zeros((12, 14, 16), np.uint8)
    labels[2:8, 3:9, 2:8] = 1
    labels[5, 5, 12] = 2
    lv = LabelVolume(labels, (1.0, 1.0, 1.0), segments=(Segment(1, "block", (1, 1, 1)), Segment(2, "dot", (1, 0, 0))))
    models = label_models(lv, device="cpu")
    assert [p.name for p in models.parts] == ["block"]
    assert [d["name"] for d in models.report["labels_without_surface"]] == ["dot"]
