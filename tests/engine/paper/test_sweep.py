"""``bonemesh sweep``: the CI run on headsq, the paper's score, composed against full runs, resume, exit codes."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from engine.cli import main
from engine.export import to_glb
from engine.export.glb import read_glb
from engine.paper.sweep import SweepConfig, run_sweep
from engine.paper.sweep_report import enhancement_score, scores
from engine.types import Volume


def _read_csv(path):
    with path.open() as fh:
        return list(csv.DictReader(fh))


def test_enhancement_score_reproduces_the_papers_table_2():
    """The paper's Table 1 rows give its Table 2 scores (MC33GPU: 66.97 + 14.64 s), to its last digit (the paper
    computed from unrounded measurements, so allow one unit there)."""
    base = {"rmse_pct": 69.48, "ssim_pct": 85.47, "reconstruct_s": 66.97, "rendering_s": 14.64}
    base |= {"faces": 5837093, "vertices": 2798075}
    best = {"rmse_pct": 74.09, "ssim_pct": 88.84, "reconstruct_s": 72.14, "rendering_s": 0.36}
    best |= {"faces": 1503286, "vertices": 750127}
    s = enhancement_score(best, base)
    assert s["score"] == pytest.approx(0.2641, abs=1e-4)
    assert round(100 * s["accuracy"], 2) == 5.29 and round(100 * s["size"], 2) == 73.72
    assert round(100 * s["time"], 2) == 11.16
    worst = {"rmse_pct": 74.28, "ssim_pct": 88.89, "reconstruct_s": 115.67, "rendering_s": 2.62}
    worst |= {"faces": 4863552, "vertices": 2427460}
    assert enhancement_score(worst, base)["score"] == pytest.approx(0.0326, abs=1e-4)


def test_glb_round_trip_reads_back_the_mesh():
    v = np.array([[0, 0, 0], [0, 0, 1], [0, 1, 0], [1, 0, 0]], np.float32)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
    pos, nrm, idx = read_glb(to_glb(v, f))
    assert pos.shape == (4, 3) and nrm.shape == (4, 3)
    np.testing.assert_array_equal(idx, f)
    np.testing.assert_allclose(np.abs(pos).sum(axis=1) * 1000, [0, 1, 1, 1], atol=1e-6)


def test_sweep_on_headsq(tmp_path, device):
    """The CI sweep: headsq, two reductions x two iteration counts, through the CLI."""
    out = tmp_path / "sweep"
    args = ["sweep", "--demo", "-o", str(out), "--reductions", "0.2,0.5", "--iterations", "1,5"]
    args += ["--repeats", "1", "--points", "20000", "--slices", "0", "--device", device, "--quiet"]
    assert main(args) == 0
    names = {p.name for p in out.iterdir()}
    assert {"meta.json", "rows.jsonl", "table1.csv", "table2.csv", "tables.md"} <= names
    for png in ("accuracy_vs_faces.png", "time_vs_iterations.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = _read_csv(out / "table1.csv")
    assert [r["method"] for r in rows] == ["MC33", "MC33GPU", "GMC33GPU"] + ["EMC33GPU"] * 4
    mc, gpu, gauss, *emc = rows
    assert float(gauss["mean_mm"]) < 1e-4 and float(gauss["volume_change_pct"]) == 0.0  # the distance reference
    assert int(gpu["faces"]) > int(emc[2]["faces"]) > int(emc[0]["faces"])  # R = 0.5 keeps more than 0.2
    for a, b in (emc[:2], emc[2:]):  # smoothing moves vertices only
        assert (a["faces"], a["vertices"]) == (b["faces"], b["vertices"])
    assert all(r["watertight"] == "True" for r in (gpu, gauss, *emc))
    # the undecimated MC33 surface of the scan cuts each slice exactly along its threshold
    assert float(gpu["rmse_pct"]) == 100.0 and float(gpu["dice"]) == 1.0
    assert int(gpu["slices_compared"]) == 93
    assert float(mc["rmse_pct"]) > 99.0
    for r in emc:
        assert 80.0 < float(r["rmse_pct"]) < 100.0 and 0.85 < float(r["dice"]) < 1.0
        assert float(r["mean_mm"]) < 0.5 and abs(float(r["volume_change_pct"])) < 2.0  # voxels are 1.5-3.2 mm
    table2 = _read_csv(out / "table2.csv")
    assert len(table2) == 4 and sum(r["best"] == "True" for r in table2) == 1
    recomputed = scores([json.loads(line) for line in (out / "rows.jsonl").read_text().splitlines()])
    np.testing.assert_allclose([float(r["score"]) for r in table2], [s["score"] for s in recomputed])
    md = (out / "tables.md").read_text()
    assert "Table 1." in md and "Table 2." in md and md.count("**") == 2


@pytest.fixture(scope="module")
def small_bone() -> Volume:
    from engine.data.phantom import bone_phantom

    return Volume(bone_phantom((24, 40, 40)), (0.25, 0.25, 0.25))


def test_composed_rows_equal_full_runs_and_resume_adds_rows(tmp_path, small_bone, device):
    from engine.data.phantom import BONE_LEVEL

    cfg = SweepConfig(reductions=(0.5,), iterations=(1, 3), repeats=1, n_points=5000, mc33_reference=False)
    composed = run_sweep(small_bone, BONE_LEVEL, tmp_path / "a", cfg, device=device, log=lambda s: None)
    full = run_sweep(
        small_bone, BONE_LEVEL, tmp_path / "b", SweepConfig(**{**cfg.__dict__, "full_runs": True}), device=device,
        log=lambda s: None,
    )  # fmt: skip
    assert len(composed) == len(full) == 4
    for a, b in zip(composed, full, strict=True):
        keys = ("method", "faces", "vertices", "watertight")
        assert [a[k] for k in keys] == [b[k] for k in keys]
        assert a["rmse_pct"] == pytest.approx(b["rmse_pct"], abs=1e-9)
        assert a["mean_mm"] == pytest.approx(b["mean_mm"], rel=1e-5, abs=1e-7)
    more = SweepConfig(**{**cfg.__dict__, "iterations": (1, 3, 7)})
    seen: list[str] = []
    rows = run_sweep(small_bone, BONE_LEVEL, tmp_path / "a", more, device=device, resume=True, log=seen.append)
    assert len(rows) == 5 and len((tmp_path / "a" / "rows.jsonl").read_text().splitlines()) == 5
    assert sum("EMC33GPU" in line for line in seen) == 1  # only the new pair was measured


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["missing.zip", "--iso", "1"], "does not exist"),
        (["--demo", "--reductions", "0,0.5"], "reduction factors"),
        (["--demo", "--crop", "0:5,:,:"], "too small"),
        (["--phantom", "4,4,4"], "at least 8"),
    ],
)
def test_bad_input_exits_2(tmp_path, capsys, args, message):
    assert main(["sweep", *args, "-o", str(tmp_path / "o"), "--device", "cpu", "--quiet"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
