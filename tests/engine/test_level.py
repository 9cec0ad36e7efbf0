"""The automatic iso level (engine.level): strictly between Otsu's classes, and the HU + 1024 hint."""

from __future__ import annotations

import numpy as np
import pytest

from engine.level import choose_level, hu1024_hint, otsu_level
from engine.params import ReconParams
from engine.pipeline import reconstruct
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


def test_hu_plus_1024_stack_is_recognised_and_the_user_told():
    vol = Volume(hu_plus_1024_head(), (1.0, 1.0, 1.0))
    hint = hu1024_hint(vol)
    assert hint is not None and "--preset bone --hu-offset 1024" in hint
    level, how = choose_level(vol, ReconParams())
    assert level < 1024 and "HU + 1024" in how  # Otsu is a skin level: said, with the way to bone
    assert hu1024_hint(Volume(hu_plus_1024_head().astype(np.float32), (1.0, 1.0, 1.0))) is None  # not integer
    assert hu1024_hint(Volume(hu_plus_1024_head().astype(np.int16) - 1024, (1.0, 1.0, 1.0), units="HU")) is None
    binary = Volume((hu_plus_1024_head() > 1500).astype(np.uint8) * 255, (1.0, 1.0, 1.0))
    assert hu1024_hint(binary) is None and "HU" not in choose_level(binary, ReconParams())[1]


def test_real_cranium_png_gets_the_hint():
    from engine.io import load_volume
    from tests.conftest import shared_file

    vol = load_volume(shared_file("cranium_ct", "cranium_ct_png16.zip"), spacing_zyx_mm=(1.5, 0.957, 0.957))
    level, how = choose_level(vol, ReconParams())
    assert "--preset bone --hu-offset 1024" in how and level < 1024
