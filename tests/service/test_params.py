"""Job parameters end to end in-process: what a client sends, the job record the API keeps, and the engine's
``ReconParams`` the worker builds from that record. Left out, every step keeps the engine's default (speck removal
and the body mask on); the engine's optional steps are reachable from the API. One row per case."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from core.params import JobParams
from engine.data import HEADSQ_ZIP
from engine.params import BodyMaskParams, IslandParams, OrientParams, PreprocessParams, ReconParams
from tests.service.checks import assert_problem
from worker.tasks import job_spec_of

KEY = {"X-API-Key": "key-a"}
SPACING = {"spacing": [1.5, 3.2, 3.2]}  # the bundled headsq PNG stack needs it
DEFAULT = ReconParams()


def _with(**changes: Any) -> ReconParams:
    return dataclasses.replace(DEFAULT, **changes)


def _post(client: TestClient, params: dict[str, Any] | None) -> Any:
    files = {"file": ("scan.zip", HEADSQ_ZIP.read_bytes(), "application/zip")}
    return client.post("/v1/jobs", files=files, data={"params": json.dumps({**SPACING, **(params or {})})}, headers=KEY)


# -- accepted: the job params, and the engine's parameters the worker runs with ------------------------------------
ACCEPTED: dict[str, tuple[dict[str, Any] | None, ReconParams]] = {
    "no-params": (None, DEFAULT),
    "orient-inferior": ({"orient": {"first_slice": "inferior"}}, _with(orient=OrientParams(first_slice="inferior"))),
    "orient-flips": (
        {"orient": {"flip_lr": True, "flip_ap": True}},
        _with(orient=OrientParams(flip_lr=True, flip_ap=True)),
    ),
    "body-off": ({"body": None}, _with(body=None)),
    "body-outline": ({"body": {"outline_hu": -300}}, _with(body=BodyMaskParams(outline_hu=-300.0))),
    "specks-kept": ({"islands": None}, _with(islands=None)),
    "specks-kept-largest-only": (
        {"islands": None, "keep_largest": 2},
        _with(islands=IslandParams(keep_largest=2, min_volume_voxels=None)),
    ),
    "speck-size-in-voxels": ({"islands": {"min_volume_voxels": 27}}, _with(islands=IslandParams(min_volume_voxels=27))),
    "min-island-mm3": ({"min_island_mm3": 5}, _with(islands=IslandParams(min_volume_mm3=5.0))),
    "both-off": ({"body": None, "islands": None}, _with(body=None, islands=None)),
    "preprocess": (
        {"preprocess": {"threshold": 100, "area_opening_px": 4, "canny_sigma": 1.5}},
        _with(preprocess=PreprocessParams(threshold=100.0, area_opening_px=4, canny_sigma=1.5)),
    ),
    "preprocess-threshold-only": ({"preprocess": {"threshold": -50}}, _with(preprocess=PreprocessParams(-50.0))),
}


@pytest.mark.parametrize("kind", list(ACCEPTED))
def test_job_params_reach_the_engine_through_the_job_record(kind: str, client: TestClient) -> None:
    """The record the API stores is what the worker reads: a step sent as null must stay off there."""
    params, expected = ACCEPTED[kind]
    resp = _post(client, params)
    assert resp.status_code == 202, resp.text
    record = resp.json()["params"]
    assert record == client.get(f"/v1/jobs/{resp.json()['id']}", headers=KEY).json()["params"]
    stored = client.app.state.services.db.get(resp.json()["id"])  # what the worker reads: the engine's dict
    spec = job_spec_of(stored)
    assert spec.recon == expected, record
    assert list(spec.input.spacing_zyx_mm or ()) == SPACING["spacing"], stored.engine_params
    assert JobParams.model_validate({**SPACING, **(params or {})}).job_spec().recon == expected


def test_a_job_without_params_runs_the_engine_defaults() -> None:
    """Speck removal and the body mask are on for API jobs, as for the CLI and the library."""
    recon = JobParams().job_spec().recon
    assert recon == ReconParams()
    assert recon.islands is not None and recon.islands.min_volume_voxels == IslandParams().min_volume_voxels
    assert recon.body == BodyMaskParams()


# -- refused: 422 naming the field at upload, and ValueError from the engine where it has the field --------------
REFUSED: dict[str, tuple[dict[str, Any], str, dict[str, Any] | None]] = {
    # name: (job params, the field named, the engine's form or None when the engine has no such value)
    "first-slice-unknown": ({"orient": {"first_slice": "left"}}, "first_slice", {"orient": {"first_slice": "left"}}),
    "orient-unknown-key": ({"orient": {"flip_si": True}}, "flip_si", {"orient": {"flip_si": True}}),
    "orient-null": ({"orient": None}, "orient", None),
    "flip-not-a-bool": ({"orient": {"flip_lr": "sideways"}}, "flip_lr", None),
    "outline-hu-nan": ({"body": {"outline_hu": float("nan")}}, "outline_hu", {"body": {"outline_hu": 1e999 * 0}}),
    "outline-hu-inf": ({"body": {"outline_hu": float("inf")}}, "outline_hu", {"body": {"outline_hu": 1e999}}),
    "body-unknown-key": ({"body": {"dilate": 3}}, "dilate", {"body": {"dilate": 3}}),
    "body-false": ({"body": False}, "body", None),
    "speck-voxels-negative": (
        {"islands": {"min_volume_voxels": -1}},
        "min_volume_voxels",
        {"islands": {"min_volume_voxels": -1}},
    ),
    "speck-voxels-inf": ({"islands": {"min_volume_voxels": float("inf")}}, "min_volume_voxels", None),
    "specks-kept-and-min-island": ({"islands": None, "min_island_mm3": 5}, "min_island_mm3", None),
    "threshold-inf": ({"preprocess": {"threshold": float("inf")}}, "threshold", {"preprocess": {"threshold": 1e999}}),
    "area-opening-zero": (
        {"preprocess": {"area_opening_px": 0}},
        "area_opening_px",
        {"preprocess": {"area_opening_px": 0}},
    ),
    "area-opening-fraction": ({"preprocess": {"area_opening_px": 2.5}}, "area_opening_px", None),
    "canny-sigma-zero": ({"preprocess": {"canny_sigma": 0}}, "canny_sigma", {"preprocess": {"canny_sigma": 0}}),
    "canny-sigma-huge": ({"preprocess": {"canny_sigma": 1e6}}, "canny_sigma", {"preprocess": {"canny_sigma": 1e6}}),
    "preprocess-crop": ({"preprocess": {"crop_zyx_mm": [[0, 1], [0, 1], [0, 1]]}}, "crop_zyx_mm", None),
}


@pytest.mark.parametrize("kind", list(REFUSED))
def test_bad_new_params_are_refused_by_the_api_and_the_engine(kind: str, client: TestClient) -> None:
    params, field, engine = REFUSED[kind]
    body = assert_problem(_post(client, params), 422)
    assert field in json.dumps(body.get("errors")), body
    with pytest.raises(ValueError):
        JobParams.model_validate(params)
    if engine is not None:
        with pytest.raises(ValueError):
            ReconParams.from_dict(engine)
    jobs = Path(client.app.state.data_dir) / "jobs"  # type: ignore[attr-defined]
    assert not [p for p in jobs.rglob("*") if p.is_file()], "a refused upload left files behind"


def test_a_spacing_that_looks_swapped_is_warned_in_the_apis_words():
    """[0.957, 0.957, 1.5] is x, y, z in most READMEs; the API's order is [z, y, x]: accepted, and warned about."""
    (warning,) = JobParams.model_validate({"spacing": [0.957, 0.957, 1.5]}).warnings()
    assert warning["code"] == "voxel_size_order" and warning["likely_zyx_mm"] == [1.5, 0.957, 0.957]
    assert 'send "spacing": [1.5, 0.957, 0.957]' in warning["message"]
    assert JobParams.model_validate({"spacing": [1.5, 0.957, 0.957]}).warnings() == []
    assert JobParams().warnings() == []
