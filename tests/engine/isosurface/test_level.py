"""The automatic iso level (engine.level): strictly between Otsu's classes, the bone preset on CT stored as HU + an
offset, and the warning when a model looks like skin."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from engine.errors import InputError
from engine.level import (
    LevelChoice,
    choose_level,
    detect_hu_offset,
    model_warnings,
    otsu_level,
    resolve_level,
    skin_warning,
)
from engine.params import IsoParams, ReconParams
from engine.job.pipeline import reconstruct
from engine.types import Volume


def test_binary_stack_gets_the_midpoint_and_a_surface():
    """0/255 (the shrew micro-CT): Otsu alone says 0, where every sample counts as above and no surface is left."""
    z, y, x = np.indices((16, 18, 20))
    data = np.where((z - 8) ** 2 + (y - 9) ** 2 + (x - 10) ** 2 < 36, 255, 0).astype(np.uint8)
    vol = Volume(data, (0.0041, 0.0041, 0.0041))
    level, how = choose_level(vol, ReconParams())
    assert level == 127.5 and how.startswith("Otsu")
    recon = reconstruct(vol, ReconParams(decimate=None, smooth=None), device="cpu")
    assert recon.report["iso_level"]["value"] == 127.5 and recon.report["mesh"]["watertight"]
    assert recon.report["mesh"]["components"] == 1


@pytest.mark.parametrize("values", [(0, 1), (10, 11, 90, 91), (-5.0, -4.5, 7.25, 8.0)])
def test_level_lies_strictly_between_the_classes(values):
    sample = np.repeat(np.asarray(values, np.float64), 50)
    level = otsu_level(sample)
    below, above = sample[sample < level], sample[sample > level]
    assert below.size + above.size == sample.size  # no sample equals the level
    assert level == (below.max() + above.min()) / 2


def test_real_binary_shrew_gets_127_5():
    from engine.io import load_volume
    from tests.conftest import shared_file

    path = shared_file("shrew_trabecular_microct", "shrew_trabecular_png16.zip")
    vol = load_volume(path, spacing_zyx_mm=(0.0041,) * 3)
    assert choose_level(vol, ReconParams())[0] == 127.5


def hu_plus_1024_head() -> np.ndarray:
    rng = np.random.default_rng(1)
    _z, y, x = np.indices((24, 48, 48))
    r = np.hypot(y - 24, x - 24)
    hu = np.where(r < 20, 40.0, -1000.0) + np.where((r > 15) & (r < 18), 900.0, 0.0)
    return np.clip(hu + 1024 + rng.normal(0, 15, hu.shape), 0, 4000).astype(np.uint16)


def test_hu_plus_1024_stack_gets_the_bone_preset_and_says_why():
    """Automatic on a stack of HU + 1024 was Otsu's level between air and soft tissue: a skin surface."""
    vol = Volume(hu_plus_1024_head(), (1.0, 1.0, 1.0))
    found = detect_hu_offset(vol)
    assert found is not None and found.offset == 1024 and 974 <= found.tissue <= 1114 and found.air < 124
    choice = resolve_level(vol, ReconParams())
    assert choice.value == 1324.0 and choice.hu_offset == 1024.0 and choice.hu_offset_from == "detected"
    assert choice.how.startswith("bone preset") and "CT stored as HU + 1024 detected" in choice.how
    entry = choice.report("raw")
    assert entry["chosen_by"] == choice.how and entry["hu_offset_detected"]["offset"] == 1024.0
    # a HU preset without hu_offset uses the detected offset (it was refused: "not calibrated in HU")
    assert choose_level(vol, ReconParams(iso=IsoParams(preset="compact-bone")))[0] == 662.0 + 1024
    # a given level is the stack's own: nothing is reinterpreted
    assert resolve_level(vol, ReconParams(iso=IsoParams(iso=600.0))) == LevelChoice(600.0, "given", None, None)
    # the same CT as float32, as int16 HU without a label, and shifted into uint16 by 32768
    assert detect_hu_offset(Volume(hu_plus_1024_head().astype(np.float32), (1.0, 1.0, 1.0))).offset == 1024
    hu = hu_plus_1024_head().astype(np.int16) - 1024
    assert detect_hu_offset(Volume(hu, (1.0, 1.0, 1.0))).offset == 0
    assert choose_level(Volume(hu, (1.0, 1.0, 1.0)), ReconParams())[0] == 300.0
    shifted = (hu.astype(np.int32) + 32768).astype(np.uint16)
    assert choose_level(Volume(shifted, (1.0, 1.0, 1.0)), ReconParams())[0] == 300.0 + 32768
    assert detect_hu_offset(Volume(hu, (1.0, 1.0, 1.0), units="HU")) is None  # HU data need no detection


def test_binary_segmented_and_micro_ct_stacks_are_not_taken_for_ct():
    binary = Volume((hu_plus_1024_head() > 1500).astype(np.uint8) * 255, (1.0, 1.0, 1.0))
    assert detect_hu_offset(binary) is None and choose_level(binary, ReconParams())[1].startswith("Otsu")
    as_4000 = Volume((hu_plus_1024_head() > 1500).astype(np.uint16) * 4000, (1.0, 1.0, 1.0))
    assert detect_hu_offset(as_4000) is None  # air at 0, but no soft-tissue peak near 1024
    rng = np.random.default_rng(0)
    z, y, x = np.indices((40, 40, 40))
    rods = np.sin(z / 4) * np.sin(y / 5) * np.sin(x / 3) > 0.3
    for background, marrow, bone in ((0, 300, 2500), (2000, 9000, 30000), (10, 60, 200)):
        micro = (np.where(rods, bone, marrow) + rng.normal(0, 0.05 * bone, rods.shape)).astype(np.float32)
        micro[:4] = background
        vol = Volume(np.clip(micro, 0, 65535).astype(np.uint16), (0.01, 0.01, 0.01))
        assert detect_hu_offset(vol) is None, (background, marrow, bone)
        with pytest.raises(InputError, match="does not look like CT"):
            choose_level(vol, ReconParams(iso=IsoParams(preset="bone")))


@pytest.mark.parametrize(
    ("folder", "name", "spacing", "offset"),
    [
        ("cranium_ct", "cranium_ct_png16.zip", (1.5, 0.957, 0.957), 1024.0),
        ("pelvis_ct", "pelvis_ct_png16.zip", (5.0, 1.663, 1.663), 1024.0),
        ("headsq_ct", "headsq_png16.zip", (1.5, 3.2, 3.2), 1024.0),  # raw scanner values: air 0, tissue 1050
        ("shrew_trabecular_microct", "shrew_trabecular_png16.zip", (0.0041,) * 3, None),  # binary micro-CT
    ],
)
def test_real_stacks_offset_and_automatic_level(folder, name, spacing, offset):
    from engine.io import load_volume
    from tests.conftest import shared_file

    vol = load_volume(shared_file(folder, name), spacing_zyx_mm=spacing)
    choice = resolve_level(vol, ReconParams())
    assert choice.hu_offset == offset
    if offset is None:
        assert choice.value == 127.5 and choice.how.startswith("Otsu")
    else:  # the skull or the pelvis at 300 HU, not the skin at Otsu's level (623.5 on the cranium)
        assert choice.value == 1324.0 and "CT stored as HU + 1024 detected" in choice.how


def test_a_stack_that_only_may_be_hu_plus_1024_keeps_otsu_with_a_warning():
    """A hollow head phantom: air, a little soft tissue, a wide partial-volume tail; the hint of earlier releases
    fires, the stricter detection does not: Otsu's level, and a warning that says how to ask for bone."""
    rng = np.random.default_rng(3)
    kind = rng.choice(3, size=(40, 40, 40), p=[0.8, 0.03, 0.17])
    data = np.where(kind == 0, rng.normal(24, 15, kind.shape), rng.normal(1064, 15, kind.shape))
    data = np.where(kind == 2, rng.uniform(200, 3000, kind.shape), data)
    vol = Volume(np.clip(data, 0, 4000).astype(np.uint16), (1.0, 1.0, 1.0))
    assert detect_hu_offset(vol) is None
    choice = resolve_level(vol, ReconParams())
    assert choice.how.startswith("Otsu") and choice.hu_offset is None
    codes = [w["code"] for w in model_warnings(vol, choice)]
    assert "maybe_hu_offset" in codes
    assert model_warnings(Volume(hu_plus_1024_head(), (1.0, 1.0, 1.0)), resolve_level(
        Volume(hu_plus_1024_head(), (1.0, 1.0, 1.0)), ReconParams())) == []  # fmt: skip


# ---- a model that still looks like skin ---------------------------------------------------------------------------
def test_a_skin_level_is_flagged_and_a_bone_level_is_not():
    vol = Volume(hu_plus_1024_head(), (1.0, 1.0, 1.0))
    skin = skin_warning(vol, 524.0, 1024.0)  # -500 HU: the outline of the head
    assert skin is not None and skin["code"] == "looks_like_skin" and skin["body_share"] > 0.9
    assert skin_warning(vol, 1324.0, 1024.0) is None
    # unknown units: a second, brighter class inside the model
    unknown = skin_warning(vol, 524.0, None)
    assert unknown is not None and unknown["code"] == "looks_like_skin" and "brighter class" in unknown["message"]
    assert skin_warning(vol, 1324.0, None) is None
    binary = Volume((hu_plus_1024_head() > 1500).astype(np.uint8) * 255, (1.0, 1.0, 1.0))
    assert skin_warning(binary, 127.5, None) is None  # a segmentation is what it is


def test_the_report_and_its_warnings_say_when_the_model_is_skin():
    vol = Volume(hu_plus_1024_head(), (1.0, 1.0, 1.0))
    params = ReconParams(decimate=None, smooth=None)
    bone = reconstruct(vol, params, device="cpu").report
    assert bone["iso_level"]["value"] == 1324.0 and bone["iso_level"]["hu_offset_from"] == "detected"
    assert bone["warnings"] == [] and bone["body_mask"]["applied"]  # the body mask runs on a detected offset
    skin = reconstruct(vol, dataclasses.replace(params, iso=IsoParams(iso=524.0, hu_offset=1024.0)), device="cpu")
    assert [w["code"] for w in skin.report["warnings"]] == ["looks_like_skin"]


def test_warnings_measured_beside_the_stages_fail_as_the_preprocess_stage(monkeypatch):
    """The warnings run on a thread while the device stages run: their failure still fails the job, named as the
    preprocess stage's, and a second job after it runs as before."""
    from engine.errors import StageError
    from engine.job import plans

    def broken(volume, choice):
        raise RuntimeError("the sample could not be read")

    monkeypatch.setattr(plans, "model_warnings", broken)
    vol = Volume(hu_plus_1024_head(), (1.0, 1.0, 1.0))
    params = ReconParams(decimate=None, smooth=None, iso=IsoParams(iso=524.0, hu_offset=1024.0))
    with pytest.raises(StageError, match="stage 'preprocess' failed: RuntimeError: the sample could not be read"):
        reconstruct(vol, params, device="cpu")
    monkeypatch.undo()
    assert [w["code"] for w in reconstruct(vol, params, device="cpu").report["warnings"]] == ["looks_like_skin"]


def test_real_cranium_skin_level_is_flagged():
    from engine.io import load_volume
    from tests.conftest import shared_file

    vol = load_volume(shared_file("cranium_ct", "cranium_ct_png16.zip"), spacing_zyx_mm=(1.5, 0.957, 0.957))
    skin = skin_warning(vol, 623.5, 1024.0)  # the old automatic level
    assert skin is not None and skin["body_share"] > 0.9
    assert skin_warning(vol, 623.5, None) is not None  # also when the offset is not known
    assert skin_warning(vol, 1324.0, 1024.0) is None and skin_warning(vol, 1324.0, None) is None
