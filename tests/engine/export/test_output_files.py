"""engine.export.files, the one registry of output files, held to what reads it: the writer (the files written and
their order), the README's table, the exporters' table, the report's triangle counts, and the API's light import."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from engine.export.files import (
    DEFAULT_FILES,
    EXPORTERS,
    FILES,
    MODEL_DCM,
    OPEN_STL,
    PRINT_STL,
    REPORT_JSON,
    engine_files,
    exporter_of,
    triangle_count,
    viewing_files,
)

REPO = Path(__file__).resolve().parents[3]


def _readme_table() -> dict[str, str]:
    """The README's table "Which file for which viewer": file name -> its "for" column."""
    section = (REPO / "README.md").read_text().split("### Which file for which viewer\n", 1)[1]
    rows: dict[str, str] = {}
    for line in section.lstrip("\n").splitlines():
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells[0] in ("file", "---"):
            continue
        rows[cells[0].strip("`")] = cells[1]
    return rows


def test_the_readme_table_lists_a_default_jobs_files_as_the_registry_does():
    table = _readme_table()
    assert len(table) >= 8, table  # the table was found and read
    assert table == {name: FILES[name].purpose for name in DEFAULT_FILES}


def test_the_registry_names_each_file_once_with_its_own_kind():
    assert list(FILES) == [
        "model.stl",
        "surface_open.stl",
        "model.glb",
        "phone.glb",
        "ar.glb",
        "phone_meshopt.glb",
        "model.usdz",
        "preview.png",
        "report.json",
        "model.dcm",
        "implant.stl",
        "defect.json",
        "labels.zip",
        "labels.dcm.zip",
    ]
    kinds = [f.kind for f in FILES.values()]
    assert len(set(kinds)) == len(kinds), kinds
    assert all(f.name == name and f.media_type.count("/") == 1 and f.purpose for name, f in FILES.items())
    # a closed surface's STL is the print model; an open one is written under its own name instead; PACS only: DICOM
    assert engine_files(closed=True) == DEFAULT_FILES and PRINT_STL in DEFAULT_FILES and OPEN_STL not in DEFAULT_FILES
    assert engine_files(closed=False) == tuple(OPEN_STL if n == PRINT_STL else n for n in DEFAULT_FILES)
    assert MODEL_DCM not in engine_files(True) + engine_files(False) and FILES[MODEL_DCM].when == "pacs"
    # a job that asked for the defect also has its answer (defect.json) and, when one was made, the template
    assert engine_files(closed=True, defect=True) == (*DEFAULT_FILES, "implant.stl", "defect.json")
    assert [f.name for f in FILES.values() if f.parts] == ["model.glb", "phone.glb", "ar.glb"]
    # a label job (a segmentation, a CT's pieces): a node per label in the GLB files, an STL per label in a zip
    assert engine_files(labels=True) == ("model.glb", "phone.glb", "ar.glb", "preview.png", "report.json", "labels.zip")
    assert all(FILES[n].parts for n in engine_files(labels=True) if n.endswith(".glb"))
    assert "labels.zip" not in engine_files(True) + engine_files(False) + engine_files(True, defect=True)
    # a PACS label job: one Encapsulated STL per label (worker.pacs), never written by the engine
    assert FILES["labels.dcm.zip"].when == "pacs" and "labels.dcm.zip" not in engine_files(labels=True)
    viewing = ["phone.glb", "ar.glb", "phone_meshopt.glb", "model.usdz", "preview.png"]
    assert [f.name for f in viewing_files()] == viewing


def test_the_exporters_table_is_read_from_the_registry_and_resolves_each_exporter():
    from engine.export.draco import to_draco_glb
    from engine.export.glb import to_glb
    from engine.export.stl import to_stl

    assert set(EXPORTERS) == {"stl", "glb", "draco_glb", "meshopt_glb", "usdz", "preview_png", "encapsulated_stl"}
    assert EXPORTERS["stl"] is to_stl and EXPORTERS["glb"] is to_glb and EXPORTERS["draco_glb"] is to_draco_glb
    for f in FILES.values():
        if f.exporter is None:
            with pytest.raises(KeyError, match="no exporter"):
                exporter_of(f)
        else:
            assert exporter_of(f.name) is EXPORTERS[f.format or ""], f.name
    assert FILES[REPORT_JSON].exporter is None and FILES[REPORT_JSON].format is None


def test_reading_the_registry_loads_no_exporter_numpy_or_warp():
    """The API and ``core`` read the registry: it names its exporters as text, imported only when asked for."""
    heavy = ["numpy", "warp", "DracoPy", "engine.export.glb", "engine.export.draco", "engine.export.stl"]
    code = (
        "import sys\nimport engine.export, engine.export.files, engine.report\n"
        f"print([m for m in {heavy!r} if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """A small sphere's files (closed, and as an open surface), with copies budgets small enough to differ."""
    from engine.job.outputs import write_outputs
    from engine.params import ReconParams
    from engine.job.pipeline import reconstruct
    from engine.types import Volume

    z, y, x = np.mgrid[:22, :24, :26].astype(np.float32)
    vol = Volume((200.0 - 20 * np.sqrt((z - 10) ** 2 + (y - 11) ** 2 + (x - 12) ** 2)).astype(np.float32), (1, 1, 1))
    out = {}
    for closed in (True, False):
        params = ReconParams.from_dict(
            {
                "iso": {"iso": 50.0, "closed": closed},
                "decimate": None,
                "export": {"phone_max_triangles": 600, "ar_max_triangles": 300},
            }
        )
        recon = reconstruct(vol, params, device="cpu")
        folder = tmp_path_factory.mktemp("closed" if closed else "open")
        out[closed] = recon, write_outputs(recon, folder, params, device="cpu")
    return out


@pytest.mark.parametrize("closed", [True, False])
def test_the_writer_writes_the_registrys_files_in_its_order(written, closed):
    _, paths = written[closed]
    assert list(paths) == list(engine_files(closed))
    assert all(p.name == name and p.stat().st_size > 0 for name, p in paths.items())
    report = json.loads(paths[REPORT_JSON].read_text())
    assert set(report["exports"]) == set(paths) - {REPORT_JSON}  # every other file is accounted for, by name
    assert all(report["exports"][name]["bytes"] == p.stat().st_size for name, p in paths.items() if name != REPORT_JSON)


def test_the_triangle_counts_are_the_files_own(written):
    from engine.export.glb import read_glb

    recon, paths = written[True]
    counts = {name: triangle_count(name, recon.report) for name in paths}
    stl = paths[PRINT_STL].read_bytes()
    assert counts[PRINT_STL] == int.from_bytes(stl[80:84], "little") == recon.report["mesh"]["n_faces"]
    assert counts["model.glb"] == len(read_glb(paths["model.glb"].read_bytes())[2])
    assert counts["ar.glb"] == len(read_glb(paths["ar.glb"].read_bytes())[2]) <= 300
    assert 300 < counts["phone.glb"] <= 600 and counts["phone_meshopt.glb"] == counts["phone.glb"]
    assert counts["model.usdz"] == counts["ar.glb"]
    assert counts["preview.png"] is None and counts[REPORT_JSON] is None
    assert triangle_count(MODEL_DCM, recon.report) == counts[PRINT_STL]
    assert triangle_count("notes.txt", recon.report) is None
