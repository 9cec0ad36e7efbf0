"""``python -m engine`` end to end through a subprocess: outputs, exit codes, no partial files."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


def run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "engine", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])},
    )


def read_stl(path: Path) -> tuple[np.ndarray, int]:
    data = path.read_bytes()
    n = int(np.frombuffer(data[80:84], "<u4")[0])
    assert len(data) == 84 + 50 * n
    rec = np.frombuffer(data[84:], dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    return rec["v"], n


def test_demo_writes_a_watertight_stl_in_mm(tmp_path):
    out = tmp_path / "head.stl"
    res = run_cli("isosurface", "--demo", "-o", str(out), "--device", "cpu", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    tri, n = read_stl(out)
    assert n > 50_000
    # the headsq volume is 64 x 64 x 93 voxels of 3.2 x 3.2 x 1.5 mm: the skull spans most of it, in mm (x, y, z)
    extent = tri.reshape(-1, 3).max(axis=0) - tri.reshape(-1, 3).min(axis=0)
    assert 100 < extent[0] < 64 * 3.2 + 1 and 100 < extent[1] < 64 * 3.2 + 1 and 100 < extent[2] < 93 * 1.5 + 1
    trimesh = pytest.importorskip("trimesh")
    mesh = trimesh.load(out)
    assert mesh.is_watertight and mesh.volume > 0


def test_npy_input(tmp_path):
    z, y, x = np.indices((20, 20, 20))
    vol = (100 - ((z - 10) ** 2 + (y - 10) ** 2 + (x - 10) ** 2)).astype(np.int16)
    np.save(tmp_path / "ball.npy", vol)
    out = tmp_path / "ball.stl"
    res = run_cli(
        "isosurface",
        str(tmp_path / "ball.npy"),
        "--iso",
        "50.5",
        "--spacing",
        "2,1,1",
        "-o",
        str(out),
        "--device",
        "cpu",
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    tri, _ = read_stl(out)
    extent = tri.reshape(-1, 3).max(axis=0) - tri.reshape(-1, 3).min(axis=0)
    np.testing.assert_allclose(extent, [2 * 7.1, 2 * 7.1, 2 * 2 * 7.1], rtol=0.05)  # x, y, z in mm


@pytest.mark.parametrize(
    ("args", "reason"),
    [
        (["missing.zip", "--iso", "1"], "does not exist"),
        (["bad.zip", "--iso", "1", "--spacing", "1,1,1"], "neither a zip"),
        (["ball.npy", "--spacing", "1,1,1"], "--iso"),
        (["ball.npy", "--iso", "1"], "--spacing"),
        (["ball.npy", "--iso", "1e9", "--spacing", "1,1,1"], "no surface"),
        (["flat.npy", "--iso", "1", "--spacing", "1,1,1"], "3-D volume"),
    ],
)
def test_bad_input_exits_2_without_output(tmp_path, args, reason):
    np.save(tmp_path / "ball.npy", np.random.default_rng(0).random((6, 6, 6)).astype(np.float32))
    np.save(tmp_path / "flat.npy", np.zeros((6, 6), np.float32))
    (tmp_path / "bad.zip").write_bytes(b"not a zip")
    out = tmp_path / "out.stl"
    res = run_cli("isosurface", *args, "-o", str(out), "--device", "cpu", cwd=tmp_path)
    assert res.returncode == 2
    assert reason in res.stderr and res.stderr.count("\n") == 1
    assert not out.exists() and not list(tmp_path.glob(".out.stl.*"))


# ------------------------------------------------------------------------------------------- reconstruct
def test_reconstruct_demo_writes_every_output(tmp_path):
    out = tmp_path / "model"
    res = run_cli("reconstruct", "--demo", "-o", str(out), "--device", "cpu", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in out.iterdir()) == ["ar.glb", "model.glb", "model.stl", "phone.glb", "report.json"]
    for stage in ("isosurface", "decimate", "smooth"):
        assert stage in res.stdout  # the summary table
    assert "100.0%" in res.stderr  # the progress bars
    import json

    report = json.loads((out / "report.json").read_text())
    assert report["mesh"]["watertight"] and report["iso_level"]["value"] == 1150.0


@pytest.mark.parametrize(
    ("args", "reason"),
    [
        (["missing.zip"], "does not exist"),
        (["bad.zip"], "zip"),
        (["stack.zip"], "spacing"),
        (["ball.npy", "--spacing", "1,1,1", "--iso", "1e9"], "no surface"),
        (["ball.npy", "--spacing", "1,1,1", "--reduction", "1.5"], "reduction"),
        (["ball.npy", "--spacing", "1,1,1", "--preset", "bone"], "not calibrated in HU"),
    ],
)
def test_reconstruct_bad_input_exits_2_without_outputs(tmp_path, args, reason):
    import zipfile

    import imageio.v3 as iio

    np.save(tmp_path / "ball.npy", np.random.default_rng(0).random((6, 6, 6)).astype(np.float32))
    (tmp_path / "bad.zip").write_bytes(b"not a zip")
    with zipfile.ZipFile(tmp_path / "stack.zip", "w") as zf:
        for i in range(3):
            buf = io.BytesIO()
            iio.imwrite(buf, np.full((8, 8), i * 50, np.uint8), extension=".png")
            zf.writestr(f"s{i}.png", buf.getvalue())
    out = tmp_path / "out"
    res = run_cli("reconstruct", *args, "-o", str(out), "--device", "cpu", "--quiet", cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert reason in res.stderr and res.stderr.strip().count("\n") == 0
    assert not out.exists() or not any(out.iterdir())
