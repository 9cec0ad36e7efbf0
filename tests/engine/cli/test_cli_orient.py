"""``bonemesh orient``: absolute options, a refusal without any (exit 2, one line naming the current orientation),
``--reset`` that says it resets, nothing written when the folder is placed so already (issue 45)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from engine.cli import main
from engine.job.outputs import write_outputs
from engine.job.pipeline import reconstruct
from engine.params import IsoParams, OrientParams, ReconParams
from tests.engine.cli.test_orient import marked_volume


@pytest.fixture
def folder(tmp_path):
    """A finished model of an image stack, turned over once (first slice inferior, image top posterior)."""
    params = ReconParams(iso=IsoParams(iso=0.5), orient=OrientParams())
    write_outputs(reconstruct(marked_volume(), params, device="cpu"), tmp_path / "out", params, device="cpu")
    assert main(["orient", str(tmp_path / "out"), "--first-slice", "inferior", "--flip-ap", "--device", "cpu"]) == 0
    return tmp_path / "out"


def _orient(folder):
    return json.loads((folder / "report.json").read_text())["parameters"]["orient"]


def _stamps(folder):
    return {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}


def test_no_option_is_refused_and_changes_nothing(folder, capsys):
    capsys.readouterr()
    before = _stamps(folder)
    assert main(["orient", str(folder), "--device", "cpu"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1, err  # one line
    assert "nothing to change" in err and "first slice inferior" in err and "--reset" in err, err
    assert _orient(folder) == {"first_slice": "inferior", "flip_lr": False, "flip_ap": True}  # not undone
    assert _stamps(folder) == before


def test_reset_says_it_resets(folder, capsys):
    capsys.readouterr()
    assert main(["orient", str(folder), "--reset", "--device", "cpu"]) == 0
    out = capsys.readouterr().out
    assert "reset to the default orientation: first slice superior" in out and "(was first slice inferior" in out
    assert _orient(folder) == {"first_slice": "superior", "flip_lr": False, "flip_ap": False}
    # again: placed so already, nothing written
    before = _stamps(folder)
    assert main(["orient", str(folder), "--reset", "--device", "cpu"]) == 0
    assert "already first slice superior" in capsys.readouterr().out and _stamps(folder) == before


def test_options_are_absolute_and_repeating_writes_nothing(folder, capsys):
    capsys.readouterr()
    before = _stamps(folder)
    assert main(["orient", str(folder), "--first-slice", "inferior", "--flip-ap", "--device", "cpu"]) == 0
    assert "nothing written" in capsys.readouterr().out and _stamps(folder) == before
    assert main(["orient", str(folder), "--flip-lr", "--device", "cpu"]) == 0  # first slice left out: superior
    assert _orient(folder) == {"first_slice": "superior", "flip_lr": True, "flip_ap": False}
    assert "placed: first slice superior, image left = patient's left" in capsys.readouterr().out


def test_reset_with_an_option_is_refused(folder, capsys):
    capsys.readouterr()
    assert main(["orient", str(folder), "--reset", "--flip-lr", "--device", "cpu"]) == 2
    assert "--reset" in capsys.readouterr().err


def test_help_names_reset():
    out = subprocess.run(
        [sys.executable, "-m", "engine", "orient", "--help"], capture_output=True, text=True, check=True
    ).stdout
    assert "--reset" in out and "default None" not in out and "(left out: superior)" in out
