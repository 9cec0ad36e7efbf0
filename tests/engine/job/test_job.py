"""One job, resolved once (``engine.job``): the spec every edge builds (the API's ``JobParams.job_spec``, the CLI's
``job_spec``) with the same rules, the runtime resolved once (``auto`` with its reason; a missing device refused at
the edge), and ``run_job``'s plans (scan, labels found by content, pieces) for the worker and the CLI alike."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core.params import JobParams
from engine.cli import build_parser
from engine.cli.args import job_spec
from engine.errors import InputError, NotLabelsError
from engine.export.files import engine_files
from engine.job import InputSpec, JobSpec, OutputSpec, resolve_runtime, run_job
from engine.params import PiecesParams, ReconParams, RoiParams
from engine.types import Volume

REPO = Path(__file__).resolve().parents[3]
SMALL = {"export": {"phone_max_triangles": 2000, "ar_max_triangles": 800}}


def _cli(*flags: str) -> JobSpec:
    return job_spec(build_parser().parse_args(["reconstruct", "scan.zip", "-o", "out", *flags]))


def _api(**params: object) -> JobSpec:
    return JobParams.model_validate(params).job_spec()


@pytest.mark.parametrize(
    ("flags", "params"),
    [
        ((), {}),
        (("--reduction", "0.3"), {"reduction": 0.3}),
        (("--max-triangles", "5000"), {"max_triangles": 5000}),
        (("--keep-specks",), {"islands": None}),
        (("--keep-specks", "--keep-largest", "2"), {"islands": None, "keep_largest": 2}),
        (("--min-island-mm3", "12.5", "--keep-largest", "3"), {"min_island_mm3": 12.5, "keep_largest": 3}),
        (("--keep-outside-body",), {"body": None}),
        (("--voxel-size", "z=1.5,y=0.5,x=0.5"), {"spacing": [1.5, 0.5, 0.5]}),
        (("--labels", "--segments", "1,femur"), {"labels": True, "segments": ["1", "femur"]}),
        (("--pieces", "3", "--roi", "0:10,2:20,3:30"), {"pieces": 3, "roi": {"box": [[0, 10], [2, 20], [3, 30]]}}),
    ],
)
def test_the_cli_and_the_api_build_the_same_spec(flags: tuple[str, ...], params: dict[str, object]) -> None:
    """The same request as flags and as JSON is one ``JobSpec`` (the CLI keeps its label STL folder)."""
    cli, api = _cli(*flags), _api(**params)
    assert dataclasses.replace(cli, outputs=OutputSpec()) == api


@pytest.mark.parametrize(
    ("flags", "params", "match"),
    [
        (("--reduction", "0.3", "--max-triangles", "100"), {"reduction": 0.3, "max_triangles": 100}, "not both"),
        (("--keep-specks", "--min-island-mm3", "4"), {"islands": None, "min_island_mm3": 4}, "not both"),
        (("--labels", "--pieces", "2"), {"labels": True, "pieces": 2}, "pieces .* or labels"),
        (("--roi", "5:1,0:2,0:2"), {"roi": {"box": [[5, 1], [0, 2], [0, 2]]}}, "lo < hi"),
    ],
)
def test_one_rule_refuses_the_same_request_on_every_edge(flags: tuple[str, ...], params: dict[str, object], match: str):
    with pytest.raises(InputError, match=match):
        _cli(*flags)
    with pytest.raises(ValueError, match=match):
        _api(**params)


def test_the_defect_is_refused_on_pieces_and_labels() -> None:
    with pytest.raises(ValueError, match="defect is found on a CT"):
        _api(defect={}, pieces=2)
    with pytest.raises(ValueError, match="defect is found on a CT"):
        JobSpec(recon=ReconParams.from_dict({"defect": {}}), input=InputSpec(kind="labels"))


def test_a_spec_round_trips_through_the_job_record() -> None:
    spec = JobSpec(
        recon=ReconParams.from_dict(
            {"decimate": {"reduction": None, "max_triangles": 900}, "defect": {"side": "left"}}
        ),
        input=InputSpec(spacing_zyx_mm=(1.5, 0.5, 0.5), roi=RoiParams(((1, 9), (0, 5), (0, 5)), units="voxels")),
    )
    record = spec.to_dict()
    assert JobSpec.from_dict(record) == spec
    pieces = JobSpec(input=InputSpec(pieces=PiecesParams(count=4), segments=(1, "femur")))
    assert JobSpec.from_dict(pieces.to_dict()) == pieces
    with pytest.raises(ValueError, match="Unknown input parameters"):
        JobSpec.from_dict({**record, "input": {**record["input"], "colour": "red"}})
    older = {"recon": record["recon"], "spacing_zyx_mm": [1.5, 0.5, 0.5]}  # a record from before the spec
    assert JobSpec.from_dict(older).input == InputSpec(spacing_zyx_mm=(1.5, 0.5, 0.5))


@pytest.mark.parametrize("bad", [0, 70000, "", "x" * 65, True, 1.5])
def test_segments_are_numbers_or_names(bad: object) -> None:
    with pytest.raises(ValueError, match="segment"):
        InputSpec(segments=(bad,))  # type: ignore[arg-type]


def test_the_runtime_is_resolved_once_with_its_reason() -> None:
    from engine.backend.select import auto_spec, get_backend

    cpu = resolve_runtime("cpu", "64MiB")
    assert (cpu.backend.kind, cpu.spec, cpu.reason, cpu.budget.bytes) == ("warp", "cpu", "", 64 << 20)
    assert str(cpu.warp_device) == "cpu" and "64MiB" not in cpu.describe() and "67,108,864" in cpu.describe()
    auto = resolve_runtime("auto")
    assert auto.backend is get_backend(auto_spec()) and auto.reason.startswith("auto: ")
    assert auto.requested == "auto" and auto.spec in auto.describe()
    again = resolve_runtime(auto.backend)  # a backend is taken as it is
    assert again.backend is auto.backend and again.reason == ""
    for bad in ("gpu", "cuda:99", "opencl:99"):
        with pytest.raises(ValueError):
            resolve_runtime(bad)
    with pytest.raises(ValueError, match="png_decoder"):
        resolve_runtime("cpu", png_decoder="fast")


def test_a_missing_opencl_is_refused_before_loading_with_the_install_line(tmp_path: Path) -> None:
    """``--device opencl`` without PyOpenCL: exit 2 at once, one line naming the extra to install."""
    code = (
        "import sys; sys.modules['pyopencl'] = None\n"
        "from engine.cli import main\n"
        "sys.exit(main(['reconstruct', '--demo', '-o', 'out', '--device', 'opencl']))"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2, res.stderr
    assert "pip install 'bonemesh[opencl]'" in res.stderr and res.stderr.count("\n") == 1
    assert not (tmp_path / "out").exists()


def _phantom() -> Volume:
    from engine.data.phantom import bone_phantom

    return Volume(bone_phantom((24, 40, 40), dtype=np.int16) - np.int16(1024), (0.6, 0.5, 0.5), units="HU")


def test_run_job_picks_the_plan_from_the_spec_and_the_input(tmp_path: Path) -> None:
    from tests.engine.labels.test_labels_outputs import nifti_bytes
    from tests.engine.labels.test_labels_util import headsq_labels

    runtime = resolve_runtime("cpu")
    recon = ReconParams.from_dict(SMALL)
    seen: list[tuple[str, float]] = []
    scan = run_job(
        _phantom(), tmp_path / "scan", JobSpec(recon=recon), runtime, on_progress=lambda s, f: seen.append((s, f))
    )
    assert scan.plan == "scan" and scan.volume is not None and list(scan.paths) == list(engine_files())
    fractions = [f for _, f in seen]
    assert fractions == sorted(fractions) and fractions[-1] == pytest.approx(0.9) and seen[-1][0] == "writing"

    pieces = run_job(
        _phantom(), tmp_path / "pieces", JobSpec(recon=recon, input=InputSpec(pieces=PiecesParams(1))), runtime
    )
    assert pieces.plan == "pieces" and [r["name"] for r in pieces.report["labels"]] == ["piece_1"]

    (tmp_path / "map").write_bytes(nifti_bytes(headsq_labels()))  # no suffix: found by its content
    labels = run_job(
        tmp_path / "map", tmp_path / "labels", JobSpec(recon=recon, input=InputSpec(segments=("2",))), runtime
    )
    assert labels.plan == "labels" and labels.volume is None and [r["value"] for r in labels.report["labels"]] == [2]
    assert list(labels.paths) == list(engine_files(labels=True))

    with pytest.raises(InputError, match="segments picks among a label map"):
        run_job(_phantom(), tmp_path / "bad", JobSpec(input=InputSpec(segments=(1,))), runtime)
    np.save(tmp_path / "ct.npy", _phantom().data)
    with pytest.raises(NotLabelsError, match="holds no label map"):
        run_job(tmp_path / "ct.npy", tmp_path / "bad", JobSpec(input=InputSpec(kind="labels")), runtime)
    assert not (tmp_path / "bad").exists()


def test_the_warm_up_warms_the_backend_jobs_use() -> None:
    """A worker resolves ``auto`` once; its warm-up runs on that very backend (on PoCL: OpenCL, not Warp's CPU)."""
    from engine.job.warmup import WARMUP_SHAPE, warm_up

    runtime = resolve_runtime("auto")
    info = warm_up(runtime, png_rows=False)
    assert info["device"] == (str(runtime.warp_device) if runtime.backend.kind == "warp" else runtime.backend.label)
    assert WARMUP_SHAPE and info["seconds"] > 0
