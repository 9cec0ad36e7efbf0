"""``python -m engine`` end to end through a subprocess: outputs, exit codes, no partial files."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[3]


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
        (["ball.npy", "--iso", "1"], "--voxel-size"),
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
        (["stack.zip"], "stack.zip: the images do not say how large a voxel is; give --voxel-size Z,Y,X"),
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
    from engine.cli.args import recon_params
    from engine.params import ReconParams

    assert recon_params(parse("x.zip", "-o", "out")) == ReconParams()


def test_options_map_to_params():
    from engine.cli.args import recon_params

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
    """One order everywhere: --voxel-size is z, y, x like the API's spacing and the page's field (it was x, y, z,
    and --spacing z, y, x); named axes in any order."""
    want = (2.0, 1.0, 0.5)  # z, y, x
    assert parse("x", "-o", "o", "--voxel-size", "2,1,0.5").spacing == want
    assert parse("x", "-o", "o", "--spacing", "2,1,0.5").spacing == want
    assert parse("x", "-o", "o", "--spacing", "x=0.5,z=2,y=1").spacing == want
    assert parse("x", "-o", "o", "--voxel-size", "z=2, y=1, x=0.5").spacing == want
    from engine.cli import build_parser

    rec = next(a for a in build_parser()._actions if a.dest == "command").choices["reconstruct"]
    assert "Z,Y,X" in rec.format_usage() and "X,Y,Z" not in rec.format_help()


@pytest.mark.parametrize("bad", ["1,1", "0.5,-1,2", "x=1,y=1", "a,b,c"])
def test_bad_voxel_size_exits_2(tmp_path, bad):
    res = run_cli("reconstruct", "v.npy", "-o", "out", "--voxel-size", bad, cwd=tmp_path)
    assert res.returncode == 2 and "--voxel-size" in res.stderr


def test_summary_names_the_axes_of_the_voxel_size(tmp_path):
    z, y, x = np.indices((12, 14, 16))
    np.save(tmp_path / "ball.npy", (30 - ((z - 6) ** 2 + (y - 7) ** 2 + (x - 8) ** 2)).astype(np.int16))
    res = run_cli("reconstruct", "ball.npy", "-o", "out", "--voxel-size", "2,1,0.5", "--iso", "0.5", "--device", "cpu",
                  "--quiet", cwd=tmp_path)  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "z 2 mm, y 1 mm, x 0.5 mm" in res.stdout
    assert "unequal in-plane sizes" in res.stderr  # CT pixels are square: y 1 mm, x 0.5 mm is questioned
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
    """Libraries never import the CLI package (``engine.cli``); nothing in the engine imports benchmarks (not
    packaged)."""
    import ast

    engine = REPO / "engine"
    cli = engine / "cli"
    for path in engine.rglob("*.py"):
        tree = ast.parse(path.read_text())
        names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        names |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        assert not any(m == "benchmarks" or m.startswith("benchmarks.") for m in names), path
        if cli not in path.parents and path.name != "__main__.py":
            assert not any(m == "engine.cli" or m.startswith("engine.cli.") for m in names), path


# ------------------------------------------------------------------------------------------- issue 27: right by default
def write_png_stack(path: Path, volume: np.ndarray) -> None:
    import zipfile

    import imageio.v3 as iio

    with zipfile.ZipFile(path, "w") as zf:
        for i, image in enumerate(volume):
            buf = io.BytesIO()
            iio.imwrite(buf, image, extension=".png")
            zf.writestr(f"head/slice_{i:03d}.png", buf.getvalue())


def test_argument_errors_are_two_lines_not_the_usage_block(tmp_path):
    res = run_cli("reconstruct", "x.zip", "-o", "out", "--bogus", cwd=tmp_path)
    assert res.returncode == 2 and "usage:" not in res.stderr
    assert res.stderr.splitlines() == [
        "bonemesh: error: unrecognized arguments: --bogus",
        "try 'bonemesh reconstruct --help'",
    ]
    res = run_cli("reconstruct", "x.zip", "-o", "out", "--voxel-size", "1,2", cwd=tmp_path)
    assert res.returncode == 2 and len(res.stderr.splitlines()) == 2 and "Z,Y,X" in res.stderr


def test_missing_voxel_size_names_the_option_and_the_input(tmp_path):
    """It led with the library's name for it, spacing_zyx_mm."""
    write_png_stack(tmp_path / "cranium.zip", np.zeros((3, 8, 8), np.uint16))
    res = run_cli("reconstruct", "cranium.zip", "-o", "out", "--device", "cpu", "--quiet", cwd=tmp_path)
    assert res.returncode == 2 and res.stderr.count("\n") == 1
    assert res.stderr.startswith("bonemesh: error: cranium.zip: ") and "--voxel-size" in res.stderr
    assert "spacing_zyx_mm" not in res.stderr


def test_a_single_png_is_named_and_refused_in_one_line(tmp_path):
    import imageio.v3 as iio

    iio.imwrite(tmp_path / "one.png", np.zeros((256, 256), np.uint16))
    res = run_cli("reconstruct", "one.png", "-o", "out", "--voxel-size", "1,1,1", "--device", "cpu", cwd=tmp_path)
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "shape" not in res.stderr
    assert "one.png: the series has 1 image(s); a volume needs at least 3 slices" in res.stderr


def test_progress_is_a_bar_on_a_terminal_and_a_few_lines_in_a_log(tmp_path):
    import pty

    z, y, x = np.indices((16, 18, 20))
    np.save(tmp_path / "ball.npy", (40 - ((z - 8) ** 2 + (y - 9) ** 2 + (x - 10) ** 2)).astype(np.int16))
    args = ("reconstruct", "ball.npy", "-o", "out", "--voxel-size", "1,1,1", "--iso", "0.5", "--device", "cpu")
    log = run_cli(*args, cwd=tmp_path)  # stderr is a pipe
    assert log.returncode == 0, log.stderr
    assert "\r" not in log.stderr and 2 <= len(log.stderr.splitlines()) <= 5  # was ~130 updates
    assert log.stderr.splitlines()[-1].startswith("bonemesh: 100.0%")
    leader, follower = pty.openpty()
    try:
        proc = subprocess.Popen(
            [sys.executable, "-m", "engine", *args[:3], "out2", *args[4:]], cwd=tmp_path, stdout=subprocess.DEVNULL,
            stderr=follower, env={**os.environ, "PYTHONPATH": str(REPO)},
        )  # fmt: skip
        os.close(follower)
        seen = b""
        while True:  # read while it runs: a full terminal buffer would stop it
            try:
                chunk = os.read(leader, 65536)
            except OSError:  # EIO: the command closed the terminal
                break
            if not chunk:
                break
            seen += chunk
        proc.wait(timeout=600)
    finally:
        os.close(leader)
    assert proc.returncode == 0 and b"\r[" in seen and b"100.0%" in seen  # the bar, redrawn in place


def test_ctrl_c_says_one_line_exits_130_and_leaves_no_output_folder(tmp_path):
    import signal
    import time

    rng = np.random.default_rng(0)
    np.save(tmp_path / "noise.npy", rng.normal(0, 1, (96, 96, 96)).astype(np.float32))  # seconds of work
    proc = subprocess.Popen(
        [sys.executable, "-m", "engine", "reconstruct", "noise.npy", "-o", "out", "--voxel-size", "1,1,1", "--iso",
         "0.5", "--keep-specks", "--device", "cpu"], cwd=tmp_path, stderr=subprocess.PIPE, stdout=subprocess.PIPE,
        text=True, env={**os.environ, "PYTHONPATH": str(REPO)},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    first = proc.stderr.readline()  # the first progress line: the run has started
    assert first.startswith("bonemesh:"), first
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=120)
    lines = (first + err).splitlines()
    assert proc.returncode == 130, err
    assert lines[-1] == "bonemesh: interrupted" and "Traceback" not in err and len(lines) <= 6
    assert not (tmp_path / "out").exists()


def test_an_unfinished_run_removes_the_folder_it_created_and_only_that(tmp_path):
    from engine.cli import _removed_unless_finished

    new = tmp_path / "new"
    with pytest.raises(KeyboardInterrupt), _removed_unless_finished(new):
        new.mkdir()
        (new / "part.tmp").write_bytes(b"x")
        raise KeyboardInterrupt
    assert not new.exists()
    old = tmp_path / "old"
    old.mkdir()
    (old / "model.stl").write_bytes(b"earlier run")
    with pytest.raises(RuntimeError), _removed_unless_finished(old):
        raise RuntimeError
    assert (old / "model.stl").read_bytes() == b"earlier run"


def test_micro_ct_summary_gives_the_volume_in_digits_that_show_it(tmp_path):
    """The shrew's summary said 'volume 0 mm3' (0.03 mm3 at 4.1 um voxels)."""
    z, y, x = np.indices((24, 24, 24))
    np.save(
        tmp_path / "ball.npy", np.where((z - 12) ** 2 + (y - 12) ** 2 + (x - 12) ** 2 < 64, 255, 0).astype(np.uint8)
    )
    res = run_cli("reconstruct", "ball.npy", "-o", "out", "--voxel-size", "0.0041,0.0041,0.0041", "--device", "cpu",
                  "--quiet", cwd=tmp_path)  # fmt: skip
    assert res.returncode == 0, res.stderr
    model = next(line for line in res.stdout.splitlines() if line.startswith("model "))
    assert "volume 0 mm3" not in model
    import re

    volume = float(re.search(r"volume ([0-9.e-]+) mm3", model).group(1))
    assert volume == pytest.approx(4 / 3 * np.pi * 8**3 * 0.0041**3, rel=0.1)  # about 1.5e-4 mm3


def test_a_swapped_voxel_size_is_refused_unnamed_and_warned_named(tmp_path):
    """--voxel-size 0.957,0.957,1.5 (x, y, z, the option's old order, from an old command or a README) is refused
    with both readings named; named axes that still look swapped are warned on stderr, in the summary and report."""
    import json

    z, y, x = np.indices((12, 14, 16))
    np.save(tmp_path / "ball.npy", (30 - ((z - 6) ** 2 + (y - 7) ** 2 + (x - 8) ** 2)).astype(np.int16))
    old = run_cli("reconstruct", "ball.npy", "-o", "old", "--voxel-size", "0.957,0.957,1.5", "--iso", "0.5",
                  "--device", "cpu", "--quiet", cwd=tmp_path)  # fmt: skip
    assert old.returncode == 2 and not (tmp_path / "old").exists()
    assert "looks like an x, y, z voxel size" in old.stderr and "z=1.5,y=0.957,x=0.957" in old.stderr, old.stderr
    assert len(old.stderr.strip().splitlines()) <= 2, old.stderr
    res = run_cli("reconstruct", "ball.npy", "-o", "out", "--voxel-size", "z=0.957,y=0.957,x=1.5", "--iso", "0.5",
                  "--device", "cpu", "--quiet", cwd=tmp_path)  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "bonemesh: warning: the voxel size z 0.957, y 0.957, x 1.5 mm looks swapped" in res.stderr
    assert "--voxel-size z=1.5,y=0.957,x=0.957" in res.stderr
    assert any(line.startswith("WARNING") and "looks swapped" in line for line in res.stdout.splitlines())
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert [w["code"] for w in report["warnings"]] == ["voxel_size_order"]
    assert report["warnings"][0]["likely_zyx_mm"] == [1.5, 0.957, 0.957]
    same = run_cli("isosurface", "ball.npy", "-o", "b.stl", "--voxel-size", "x=1.5,y=0.957,z=0.957", "--iso", "0.5",
                   "--device", "cpu", cwd=tmp_path)  # fmt: skip
    assert same.returncode == 0 and "looks swapped" in same.stderr


def test_automatic_level_on_a_hu_plus_1024_stack_is_bone_and_a_skin_level_is_flagged(tmp_path):
    """Only --voxel-size on CT stored as HU + 1024 gave a skin model (3.3 L on the cranium), said on stderr only."""
    import json

    from tests.engine.isosurface.test_level import hu_plus_1024_head

    write_png_stack(tmp_path / "head.zip", hu_plus_1024_head())
    res = run_cli("reconstruct", "head.zip", "-o", "bone", "--voxel-size", "1,1,1", "--device", "cpu", "--quiet",
                  cwd=tmp_path)  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "bone preset (300 HU = 1324 stored), CT stored as HU + 1024 detected" in res.stdout
    assert "WARNING" not in res.stdout and res.stderr == ""
    report = json.loads((tmp_path / "bone" / "report.json").read_text())
    assert report["iso_level"]["value"] == 1324.0 and report["warnings"] == []
    skin = run_cli("reconstruct", "head.zip", "-o", "skin", "--voxel-size", "1,1,1", "--iso", "624", "--device", "cpu",
                   "--quiet", cwd=tmp_path)  # fmt: skip
    assert skin.returncode == 0, skin.stderr
    assert any(line.startswith("WARNING") and "skin" in line for line in skin.stdout.splitlines())
    flagged = json.loads((tmp_path / "skin" / "report.json").read_text())["warnings"]
    assert [w["code"] for w in flagged] == ["looks_like_skin"]
