"""The print model is checked before it ships (issue 15): each defect is one row; an open surface is written under
its own name and never as model.stl."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import trimesh

from engine.errors import PrintCheckError
from engine.export.printcheck import OPEN_STL, PRINT_STL, check_print_model
from engine.job.outputs import write_outputs
from engine.params import IsoParams, ReconParams
from engine.job.pipeline import Reconstruction
from engine.surface.meshcheck import mesh_stats
from engine.types import Mesh

Arrays = tuple[np.ndarray, np.ndarray]


def _box() -> Arrays:
    """A closed box, vertices in (z, y, x) order, faces outward with vertices taken in (x, y, z) order."""
    box = trimesh.creation.box(extents=(4.0, 3.0, 2.0))
    return box.vertices[:, ::-1].astype(np.float32).copy(), box.faces.astype(np.int32).copy()


def _open(v: np.ndarray, f: np.ndarray) -> Arrays:
    return v, f[1:]


def _inside_out(v: np.ndarray, f: np.ndarray) -> Arrays:
    return v, f[:, ::-1].copy()


def _one_face_flipped(v: np.ndarray, f: np.ndarray) -> Arrays:
    f = f.copy()
    f[0] = f[0, ::-1]
    return v, f


def _repeated_vertex(v: np.ndarray, f: np.ndarray) -> Arrays:
    return v, np.vstack([f, [[0, 0, 1]]]).astype(np.int32)


def _zero_area(v: np.ndarray, f: np.ndarray) -> Arrays:
    v = v.copy()
    a, b, c = f[0]
    v[c] = (v[a] + v[b]) / 2  # the face's corners become collinear; the topology stays closed
    return v, f


def _edge_in_three_faces(v: np.ndarray, f: np.ndarray) -> Arrays:
    return v, np.vstack([f, f[:1]]).astype(np.int32)


DEFECTS: dict[str, tuple[Callable[[np.ndarray, np.ndarray], Arrays], str]] = {
    "open": (_open, "watertight"),
    "inside-out": (_inside_out, "positive_volume"),
    "one-face-flipped": (_one_face_flipped, "consistently_oriented"),
    "repeated-vertex": (_repeated_vertex, "no_degenerate_faces"),
    "zero-area-face": (_zero_area, "no_degenerate_faces"),
    "edge-in-three-faces": (_edge_in_three_faces, "two_manifold"),
}


def test_a_closed_outward_box_passes() -> None:
    v, f = _box()
    result = check_print_model(v, f)
    assert result["passed"] and set(result["checks"]) >= {"watertight", "two_manifold", "positive_volume"}
    assert check_print_model(v, f, mesh_stats(v, f))["passed"]  # with the report's stats


@pytest.mark.parametrize("kind", list(DEFECTS))
def test_a_defective_print_model_is_refused(kind: str) -> None:
    make, check = DEFECTS[kind]
    v, f = make(*_box())
    with pytest.raises(PrintCheckError, match=check):
        check_print_model(v, f)


def _recon(v: np.ndarray, f: np.ndarray) -> Reconstruction:
    mesh = trimesh.Trimesh(v[:, ::-1], f, process=False)
    normals = np.asarray(mesh.vertex_normals)[:, ::-1].astype(np.float32)
    return Reconstruction(Mesh(v, f, normals), {"mesh": mesh_stats(v, f)})


def test_open_model_is_not_written_as_the_print_model(tmp_path: Path) -> None:
    v, f = _open(*_box())
    with pytest.raises(PrintCheckError, match="watertight"):
        write_outputs(_recon(v, f), tmp_path / "closed", ReconParams(), device="cpu")
    assert not list((tmp_path / "closed").rglob("*.stl")), "a failed print check left a model behind"

    params = ReconParams(iso=IsoParams(closed=False))  # --open: an open surface, differently named, unchecked
    paths = write_outputs(_recon(v, f), tmp_path / "open", params, device="cpu")
    assert OPEN_STL in paths and PRINT_STL not in paths, sorted(paths)
    assert not (tmp_path / "open" / PRINT_STL).exists()


def test_a_good_model_ships_with_its_check_in_the_report(tmp_path: Path) -> None:
    recon = _recon(*_box())
    paths = write_outputs(recon, tmp_path, ReconParams(), device="cpu")
    assert PRINT_STL in paths and recon.report["print_check"]["passed"] is True
