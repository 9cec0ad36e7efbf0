"""Progress weighted by expected stage time, progress inside stages, and loading progress."""

from __future__ import annotations

import numpy as np
import pytest

from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.io import load_volume
from engine.params import IsoParams, ReconParams
from engine.job.pipeline import STAGES, reconstruct
from engine.job.progress import STAGE_WEIGHTS, StageProgress, span


def test_weights_cover_the_stages_and_decimation_dominates():
    assert set(STAGE_WEIGHTS) == set(STAGES)
    seen: list[tuple[str, float]] = []
    p = StageProgress(STAGES, lambda s, f: seen.append((s, f)))
    for stage in STAGES:
        p.start(stage)
        if stage == "decimate":
            for k in range(1, 5):
                p.within(stage, k / 4)  # the passes
        p.end(stage)
    fractions = [f for _, f in seen]
    assert fractions == sorted(fractions) and fractions[0] == 0.0 and fractions[-1] == pytest.approx(1.0)
    dec = [f for s, f in seen if s == "decimate"]
    total = sum(STAGE_WEIGHTS.values())
    assert dec[-1] - dec[0] == pytest.approx(STAGE_WEIGHTS["decimate"] / total)
    assert len(set(dec)) == 5  # moved during the stage, not only at its ends
    assert dec[0] < 0.2  # the bar no longer sits at 62 % for the whole decimation


def test_progress_never_goes_back_and_clamps():
    seen: list[float] = []
    p = StageProgress(["a", "b"], lambda s, f: seen.append(f), weights={"a": 1.0, "b": 3.0})
    p.within("b", 0.5)
    p.start("a")  # out of order: reported at the furthest point so far
    p.within("b", 7.0)
    assert seen == [0.625, 0.625, 1.0]
    out: list[tuple[str, float]] = []
    f = span(lambda s, x: out.append((s, x)), "loading", 0.0, 0.1)
    f(0.5)
    f(2.0)
    assert out == [("loading", 0.05), ("loading", 0.1)]


def test_pipeline_progress_is_weighted():
    vol = load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)
    seen: list[tuple[str, float]] = []
    reconstruct(vol, ReconParams(iso=IsoParams(iso=1150.0)), device="cpu", on_progress=lambda s, f: seen.append((s, f)))
    assert seen[0] == ("preprocess", 0.0) and seen[-1] == ("normals", 1.0)
    start = dict(reversed(seen))
    assert start["decimate"] < 0.2 and start["smooth"] > 0.9


def test_loading_reports_slices():
    seen: list[float] = []
    vol = load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM, on_progress=seen.append)
    assert len(seen) == vol.data.shape[0] - 1 and seen[-1] == 1.0
    assert np.all(np.diff(seen) > 0)
