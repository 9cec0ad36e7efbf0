"""One label's model of a label job: ``GET /v1/jobs/{id}/labels/{value}.stl``, the STL of that label out of the job's
``labels.zip`` (so a surgeon downloads the femur, not the whole zip). The label is named by its value (the report's
``labels[].value``); the file is named by the label."""

from __future__ import annotations

import json
import zipfile
from typing import Any

from fastapi import APIRouter
from fastapi.responses import Response

from core.storage import version_of
from engine.export.files import LABELS_ZIP, REPORT_JSON
from service.deps import OwnerDep, ServicesDep
from service.problems import Problem
from service.problems import problems as errors
from service.routes.jobs import KEYED, _job

router = APIRouter(prefix="/v1", tags=["jobs"])
STL_CONTENT = {"content": {"model/stl": {"schema": {"type": "string", "format": "binary"}}}, "description": "the STL"}


@router.get(
    "/jobs/{job_id}/labels/{value}.stl",
    summary="one label's watertight STL (patient LPS mm) from a label job's labels.zip",
    response_class=Response,
    responses={
        200: STL_CONTENT,
        **KEYED,
        **errors(404, 409, d404="no such job, or no such label in it", d409="the job has not succeeded"),
    },
)
def label_stl(job_id: str, value: int, who: OwnerDep, svc: ServicesDep) -> Response:
    job = _job(svc, job_id, who)
    if job.state != "succeeded":
        raise Problem(409, f"job {job_id} is {job.state}: its labels are there once it has succeeded")
    row, data = _member(svc, job, value)
    filename = row["file"].rsplit("/", 1)[-1]
    return Response(data, media_type="model/stl", headers={"content-disposition": f'attachment; filename="{filename}"'})


def _member(svc: Any, job: Any, value: int) -> tuple[dict[str, Any], bytes]:
    """The report's row of label ``value`` and its STL's bytes, read from the job's committed outputs."""
    version = version_of(job)
    with svc.storage.local_output(job.id, REPORT_JSON, version) as report_path:
        rows = json.loads(report_path.read_text()).get("labels") if report_path is not None else None
    if not rows:
        raise Problem(404, f"job {job.id} is not a label job (it has no {LABELS_ZIP})")
    row = next((r for r in rows if r.get("value") == value and r.get("file")), None)
    if row is None:
        have = ", ".join(f"{r['value']} {r['name']!r}" for r in rows[:20])
        raise Problem(404, f"job {job.id} has no model of label {value} (it has {have})")
    with svc.storage.local_output(job.id, LABELS_ZIP, version) as zipped:
        if zipped is None:
            raise Problem(404, f"job {job.id} has no {LABELS_ZIP}")
        with zipfile.ZipFile(zipped) as zf:
            return row, zf.read(row["file"])
