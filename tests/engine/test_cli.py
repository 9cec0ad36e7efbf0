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
        (["bad.zip", "--iso", "1", "--spacing", "1,1,1"], "not a readable zip"),
        (["ball.npy", "--spacing", "1,1,1"], "--iso"),
        (["ball.npy", "--iso", "1"], "--spacing"),
        (["ball.npy", "--iso", "1e9", "--spacing", "1,1,1"], "no surface"),
        (["flat.npy", "--iso", "1", "--spacing", "1,1,1"], "at least 3 slices"),
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
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [
            "ar.glb",
            "model.glb",
            "model.stl",
            "phone.glb",
            "report.json",
            "phone_meshopt.glb",
            "model.usdz",
            "preview.png",
        ]
    )
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
        (["stack.zip"], "--voxel-size X,Y,Z"),
        (["stack.zip", "--voxel-size", "1e300,1,1"], "Expected a voxel size between 0.0001 and 100 mm, got 1e+300"),
        (["stack.zip", "--spacing", "1e-300,1,1"], "Expected a voxel size between 0.0001 and 100 mm, got 1e-300"),
        (["ball.npy", "--spacing", "1,1,1", "--reduction", "0"], "reduction must be in (0, 1], got 0"),
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


# ------------------------------------------------------------------------------------------- arguments
def parse(*argv: str):
    from engine.cli import build_parser

    return build_parser().parse_args(["reconstruct", *argv])


def test_cli_defaults_come_from_the_dataclasses():
    from engine.cli_args import recon_params
    from engine.params import ReconParams

    assert recon_params(parse("x.zip", "-o", "out")) == ReconParams()


def test_options_map_to_params():
    from engine.cli_args import recon_params

    p = recon_params(
        parse("x", "-o", "o", "--threshold", "100", "--area-opening-px", "9", "--canny-sigma", "1.5",
              "--keep-outside-body", "--keep-specks", "--first-slice", "inferior", "--flip-ap",
              "--max-triangles", "500")
    )  # fmt: skip
    assert (p.preprocess.threshold, p.preprocess.area_opening_px, p.preprocess.canny_sigma) == (100.0, 9, 1.5)
    assert p.body is None and p.islands is None
    assert (p.orient.first_slice, p.orient.flip_lr, p.orient.flip_ap) == ("inferior", False, True)
    assert p.decimate.reduction is None and p.decimate.max_triangles == 500
    assert recon_params(parse("x", "-o", "o", "--min-island-mm3", "2")).islands.min_volume_for((1, 1, 1)) == 2.0


def test_voxel_size_forms_agree():
    want = (2.0, 1.0, 0.5)  # z, y, x
    assert parse("x", "-o", "o", "--voxel-size", "0.5,1,2").spacing == want
    assert parse("x", "-o", "o", "--spacing", "2,1,0.5").spacing == want
    assert parse("x", "-o", "o", "--spacing", "x=0.5,z=2,y=1").spacing == want
    assert parse("x", "-o", "o", "--voxel-size", "z=2, y=1, x=0.5").spacing == want


@pytest.mark.parametrize("bad", ["1,1", "0.5,-1,2", "x=1,y=1", "a,b,c"])
def test_bad_voxel_size_exits_2(tmp_path, bad):
    res = run_cli("reconstruct", "v.npy", "-o", "out", "--voxel-size", bad, cwd=tmp_path)
    assert res.returncode == 2 and "--voxel-size" in res.stderr


def test_summary_names_the_axes_of_the_voxel_size(tmp_path):
    z, y, x = np.indices((12, 14, 16))
    np.save(tmp_path / "ball.npy", (30 - ((z - 6) ** 2 + (y - 7) ** 2 + (x - 8) ** 2)).astype(np.int16))
    res = run_cli("reconstruct", "ball.npy", "-o", "out", "--voxel-size", "0.5,1,2", "--iso", "0.5", "--device", "cpu",
                  "--quiet", cwd=tmp_path)  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "x 0.5 mm, y 1 mm, z 2 mm" in res.stdout
    assert "first slice superior" in res.stdout and "LPS" in res.stdout


def test_output_naming_a_file_is_a_user_error(tmp_path):
    (tmp_path / "taken").write_text("not a folder")
    res = run_cli("reconstruct", "--demo", "-o", "taken", "--device", "cpu", "--quiet", cwd=tmp_path)
    assert res.returncode == 2 and "is an existing file" in res.stderr and res.stderr.count("\n") == 1
    assert (tmp_path / "taken").read_text() == "not a folder"


def test_an_error_after_the_progress_bar_starts_on_its_own_line(tmp_path):
    np.save(tmp_path / "ball.npy", np.random.default_rng(0).random((6, 6, 6)).astype(np.float32))
    res = run_cli("reconstruct", "ball.npy", "--spacing", "1,1,1", "--iso", "1e9", "-o", "out", "--device", "cpu",
                  cwd=tmp_path)  # fmt: skip
    assert res.returncode == 2
    assert "%" in res.stderr  # the bar was drawn
    lines = res.stderr.split("\n")
    assert any(line.startswith("bonemesh: error: no surface") for line in lines)


def test_the_import_graph_has_no_cycle_through_the_cli_and_no_benchmarks():
    """Libraries never import the CLI modules; nothing in the engine imports benchmarks (not packaged)."""
    import ast

    engine = REPO / "engine"
    for path in engine.rglob("*.py"):
        tree = ast.parse(path.read_text())
        names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        names |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        assert not any(m == "benchmarks" or m.startswith("benchmarks.") for m in names), path
        if not path.name.startswith("cli") and path.name != "__main__.py":
            assert not any(m.startswith("engine.cli") for m in names), path
