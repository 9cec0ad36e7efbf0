"""Every benchmark of ``benchmarks/`` runs end to end at its smallest size on the CPU, so none rots between the GPU
sessions that run them at full size.

Each test runs the benchmark's ``main`` with the arguments of its smallest meaningful run (tiny phantoms, one
repetition, the data folder pointed at an empty one so the real scans are skipped) and writes its JSON into pytest's
temporary folder; it then checks the JSON's top-level keys and that every measured input got finite numbers and no
recorded error. Speed is never asserted: timings are only checked to be numbers. The engine benchmarks run in this
process (that is how they work); those that start processes of their own (ingest's fresh loader processes; service,
throughput and status_latency: a real redis-server, ``bonemesh serve`` and workers) run as ``python -m
benchmarks.X``, as they are run by hand, and get SIGTERM on a timeout so that they stop what they started.
``benchmarks/upload.py`` is smoke-run by ``tests/service/test_upload_benchmark.py``.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.service.procs import REPO, ProcessError, find_redis_server

PHANTOM = "16,32,32"  # the smallest bone phantom with a surface of every kind the benchmarks measure
NAME = "phantom_16x32x32"


def finite(value: Any) -> bool:
    """A real number (not a bool, not NaN or infinite)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def has_keys(report: dict[str, Any], *keys: str) -> None:
    missing = [k for k in keys if k not in report]
    assert not missing, f"missing top-level keys {missing}; the JSON has {sorted(report)}"


def load(path: Path) -> dict[str, Any]:
    assert path.is_file(), f"the benchmark wrote no {path.name}"
    report: dict[str, Any] = json.loads(path.read_text())
    return report


def run_module(module: str, args: list[str], tmp_path: Path, timeout: float = 120) -> None:
    """``python -m benchmarks.<module> args`` from the checkout; fails with its output's tail on a non-zero exit.
    On a timeout it gets SIGTERM first (the benchmarks stop their redis-server, API and workers on it)."""
    log = tmp_path / f"{module}.log"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)}
    argv = [sys.executable, "-m", f"benchmarks.{module}", *args]
    with open(log, "wb") as fh:
        proc = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env, cwd=REPO)
        try:
            rc = proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            pytest.fail(f"{' '.join(argv)} ran past {timeout:.0f} s:\n{log.read_text(errors='replace')[-6000:]}")
    assert rc == 0, f"{' '.join(argv)} exited with {rc}:\n{log.read_text(errors='replace')[-6000:]}"


@pytest.fixture(scope="module")
def redis_executable() -> str:
    """The redis-server the service benchmarks start (as the service tests' ``redis_server`` fixture finds it)."""
    try:
        return find_redis_server()
    except ProcessError as exc:
        pytest.fail(str(exc), pytrace=False)


@pytest.fixture
def no_data(tmp_path: Path) -> Path:
    """An empty data folder: the benchmarks skip the real scans (../shared/data) and run on the phantom alone."""
    folder = tmp_path / "no-data"
    folder.mkdir()
    return folder


# -- the engine, in this process -----------------------------------------------------------------------------------
def test_mc33(tmp_path: Path) -> None:
    from benchmarks.mc33 import main

    out = tmp_path / "mc33.json"
    assert main(["--device", "cpu", "--shape", PHANTOM, "--repeat", "1", "--out", str(out)]) == 0
    report = load(out)
    has_keys(report, "benchmark", "device", "shape", "voxels", "level", "results", "ratios", "versions")
    for name in ("ours", "skimage", "warp_mc", "ours_resident", "warp_mc_resident"):
        r = report["results"][name]
        assert r["available"], f"{name}: {r.get('error')}"
        assert finite(r["seconds"]) and finite(r["voxels_per_s"]) and r["triangles"] > 0, name
    assert finite(report["ratios"]["ours_over_skimage_voxels_per_s"])


def test_decimate(tmp_path: Path, no_data: Path) -> None:
    from benchmarks.decimate import main

    out = tmp_path / "decimate.json"
    args = ["--device", "cpu", "--data", str(no_data), "--phantom", PHANTOM, "--reductions", "0.5", "--repeat", "1"]
    assert main([*args, "--points", "2000", "--slices", "4", "--out", str(out)]) == 0
    report = load(out)
    has_keys(report, "benchmark", "device", "versions", "inputs")
    assert list(report["inputs"]) == [NAME]
    entry = report["inputs"][NAME]
    assert entry["mc33"]["faces"] > 0 and finite(entry["mc33"]["similarity"]["dice"])
    (row,) = entry["rows"]
    for method in ("warp", "meshlab"):  # MeshLab takes a fraction of a second on this mesh
        assert finite(row[method]["seconds"]) and row[method]["faces"] > 0, method
        assert finite(row[method]["distance"]["mean_mm"]), method
    assert all(finite(v) for v in row["ratios"].values())


def test_budget(tmp_path: Path) -> None:
    from benchmarks.budget import main

    out = tmp_path / "budget.json"
    # 2 MiB streams the phantom in slabs and tiles the decimation of the phantom stacked twice
    args = ["--device", "cpu", "--phantom", PHANTOM, "--stack", "1,2", "--budgets", "none,2MiB", "--repeat", "1"]
    assert main([*args, "--write", "--out", str(out)]) == 0
    report = load(out)
    has_keys(report, "benchmark", "device", "phantom_shape", "params", "volumes")
    assert sorted(report["volumes"]) == [NAME, "phantom_32x32x32"]
    for name, volume in report["volumes"].items():
        assert sorted(volume["runs"]) == ["2MiB", "none"], name
        for label, run in volume["runs"].items():
            assert "error" not in run and "error" not in run["write_outputs"], (name, label, run)
            assert finite(run["seconds"]) and run["faces"] > 0, (name, label)
        assert finite(volume["runs"]["2MiB"]["time_ratio_vs_unbounded"]), name
        assert "stream" in volume["runs"]["2MiB"], f"{name}: the 2 MiB budget did not stream"


def test_multi_gpu(tmp_path: Path) -> None:
    from benchmarks.multi_gpu import main

    out = tmp_path / "multi_gpu.json"
    # one device named twice: the split, the parts' pinned borders and the join, the parts in turn (CI has no GPU)
    args = ["--devices", "cpu,cpu", "--phantom", PHANTOM, "--stack", "2", "--budget", "2MiB", "--repeat", "1"]
    assert main([*args, "--out", str(out)]) == 0
    report = load(out)
    has_keys(report, "benchmark", "devices", "shape_zyx", "budget_bytes_per_device", "runs")
    assert sorted(report["runs"]) == ["1", "2"]
    for n, run in report["runs"].items():
        assert "error" not in run and finite(run["seconds"]) and run["faces"] > 0, (n, run)
    two = report["runs"]["2"]
    assert len(two["parts"]) == 2 and finite(two["speedup_vs_one"]) and two["same_mesh"] is True


def test_host_memory(tmp_path: Path) -> None:
    from benchmarks.host_memory import main

    out = tmp_path / "host_memory.json"
    # a 16 MiB bound whose share for a whole scan (0.1 %) is under the 32^3 phantom: read slab by slab
    args = ["--shape", "32,32,32", "--stack", "1", "--bound", "16MiB", "--volume-share", "0.001"]
    assert main([*args, "--formats", "npy,ome-zarr", "--out", str(out)]) == 0
    report = load(out)
    has_keys(report, "benchmark", "shape_zyx", "volume_bytes", "host_bound_bytes", "device_budget_bytes", "formats")
    assert sorted(report["formats"]) == ["npy", "ome-zarr"]
    for fmt, row in report["formats"].items():
        assert row["same_mesh"], (fmt, row)
        assert row["bounded"]["out_of_core"] and not row["whole"]["out_of_core"], fmt
        for run in (row["bounded"], row["whole"]):
            assert finite(run["seconds"]) and run["faces"] > 0 and run["used_bytes"] > 0, fmt


def test_labels_speed(tmp_path: Path) -> None:
    from benchmarks.labels_speed import main

    out = tmp_path / "labels_speed.json"
    assert main(["--device", "cpu", "--size", "16,32,32", "--labels", "4", "--repeat", "1", "--out", str(out)]) == 0
    report = load(out)
    has_keys(report, "benchmark", "device", "size_zyx", "labels_present", "warmup", "runs", "seconds_min")
    assert "error" not in report and report["labels_present"] == 4
    (run,) = report["runs"]
    assert finite(run["seconds"]) and all(finite(v) for v in run["stage_seconds"].values())
    assert run["parts"] == run["watertight_parts"] == 4 and run["faces"] > 0


def test_body_mask(tmp_path: Path) -> None:
    from benchmarks.body_mask import main

    out = tmp_path / "body_mask.json"
    args = ["--shape", "8,32,32", "--repeat", "1", "--data", str(tmp_path / "none"), "--before", str(REPO)]
    assert main([*args, "--out", str(out)]) == 0
    report = load(out)
    has_keys(report, "benchmark", "cpus", "repeat", "before", "results")
    row = report["results"]["clinical_8x32x32"]
    assert "error" not in row["after"] and finite(row["after"]["median_seconds"])
    assert row["same_result"] and finite(row["ratio_before_over_after"])  # this checkout against itself
    assert row["after"]["info"]["pieces_removed"] == 2  # the couch and the holder


def test_determinism(tmp_path: Path) -> None:
    from benchmarks.determinism import main

    out = tmp_path / "determinism.json"
    assert main(["--device", "cpu", "--phantom", PHANTOM, "--budgets", "none,8MiB", "--out", str(out)]) == 0
    report = load(out)
    has_keys(report, "device", "phantom", "results")
    assert sorted(report["results"]) == ["headsq", NAME]
    for name, rows in report["results"].items():
        assert [r["budget"] for r in rows] == [None, "8MiB"], name
        for row in rows:
            assert row["faces"] > 0 and finite(row["reconstruct_seconds"]), name
            assert len(row["mesh_sha256"]) == 64 and len(row["model_stl_sha256"]) == 64, name


def test_pipeline(tmp_path: Path, no_data: Path) -> None:
    from benchmarks.pipeline import main

    out = tmp_path / "pipeline.json"
    args = ["--device", "cpu", "--data", str(no_data), "--phantom", PHANTOM, "--repeat", "1"]
    assert main([*args, "--out", str(out)]) == 0
    report = load(out)
    has_keys(report, "benchmark", "device", "timing", "config", "parameters", "results")
    assert list(report["results"]) == [NAME]
    r = report["results"][NAME]
    assert finite(r["reconstruct_seconds"]) and finite(r["write_outputs_seconds"])
    assert all(finite(v) for v in r["stage_seconds"].values()) and r["mesh"]["n_faces"] > 0


def test_viewing_copies(tmp_path: Path) -> None:
    from benchmarks.viewing_copies import main

    out = tmp_path / "viewing_copies.json"
    # budgets under the phantom's ~900 faces, so both copies are decimated
    args = ["--device", "cpu", "--phantom", PHANTOM, "--budgets", "400,200", "--repeat", "1", "--quality"]
    assert main([*args, "--out", str(out)]) == 0
    report = load(out)
    has_keys(report, "benchmark", "device", "phantom", "timing", "reconstruct_seconds", "mesh", "results")
    r = report["results"]["400,200"]
    assert finite(r["viewing_copies_seconds"]) and finite(r["write_outputs_seconds"])
    for name in ("phone", "ar"):
        assert r[name]["summary"]["decimated"] and r[name]["topology"]["n_faces"] > 0, name
        assert finite(r[name]["distance_to_print_model"]["mean_mm"]), name


def test_opencl_stages(tmp_path: Path) -> None:
    from tests.engine.conftest import opencl_missing

    if opencl_missing():
        pytest.skip(f"OpenCL backend: {opencl_missing()}")
    from benchmarks.opencl_stages import main

    out = tmp_path / "opencl_stages.json"
    assert main(["--phantom", PHANTOM, "--repeat", "1", "--out", str(out)]) == 0  # 1: the meshes differ
    report = load(out)
    has_keys(report, "benchmark", "host", "devices", "versions", "inputs")
    assert sorted(report["inputs"]) == ["headsq", NAME]
    for name, entry in report["inputs"].items():
        assert entry["identical"], name
        for key in ("warp", "opencl"):
            assert entry[key]["faces"] > 0 and finite(entry[key]["seconds"]["total"]), (name, key)
        assert all(finite(v) for v in entry["ratios_warp_over_opencl"].values()), name


def test_backends(tmp_path: Path) -> None:
    from tests.engine.conftest import opencl_missing

    if opencl_missing():
        pytest.skip(f"OpenCL backend: {opencl_missing()}")
    from benchmarks.backends import main

    out = tmp_path / "backends.json"
    args = ["--devices", "cpu,opencl", "--no-scans", "--phantom", "24,32,32", "--labels", "4@20,32,32", "--repeat", "1"]
    assert main([*args, "--out", str(out)]) == 0
    report = load(out)
    has_keys(report, "benchmark", "host", "devices", "inputs", "min_ratio")
    scan, labels = report["inputs"].values()
    for entry in (scan, labels):
        assert entry["identical_topology"]["opencl"] and entry["identical_mesh"]["opencl"]
        assert finite(entry["ratio_first_over"]["opencl"])
    assert scan["cpu"]["topology"]["watertight"]
    assert labels["labels"] == labels["cpu"]["topology"]["watertight_parts"] == labels["cpu"]["topology"]["parts"]


# -- benchmarks that start processes of their own: python -m benchmarks.X --------------------------------------
def test_ingest(tmp_path: Path) -> None:
    out = tmp_path / "ingest.json"
    # two threads (and, for DICOM, two decode processes) whatever this machine's CPUs
    args = ["--shape", PHANTOM, "--repeat", "1", "--threads", "2", "--workdir", str(tmp_path / "work")]
    run_module("ingest", [*args, "--out", str(out)], tmp_path)
    report = load(out)
    has_keys(report, "benchmark", "machine", "host", "shape", "timing", "results")
    assert sorted(report["results"]) == ["dicom", "png"]
    for fmt, r in report["results"].items():
        assert r["same_volume"], fmt
        assert finite(r["serial_seconds"]) and finite(r["threaded_seconds"]) and finite(r["speedup"]), fmt
    assert finite(report["results"]["png"]["threaded_pillow_seconds"])
    assert finite(report["results"]["dicom"]["processes_seconds"])
    assert report["results"]["dicom"]["runs"]["processes"][0]["decode_processes_ran"] > 0


def test_status_latency(tmp_path: Path, redis_executable: str) -> None:
    out = tmp_path / "status_latency.json"
    args = ["--uploads", "4", "--shape", "8,32,32", "--pollers", "1", "--redis-server", redis_executable]
    run_module("status_latency", [*args, "--workdir", str(tmp_path / "work"), "--out", str(out)], tmp_path)
    report = load(out)
    has_keys(report, "benchmark", "uploads", "archive_bytes", "shape_zyx", "pollers", "workers", "machine", "rounds")
    (r,) = report["rounds"]
    assert r["upload_statuses"] == [202] and r["status_errors"] == []
    assert r["status_reads"] > 0 and finite(r["status_ms"]["p50"]) and finite(r["uploads_wall_s"])


def test_service(tmp_path: Path, no_data: Path, redis_executable: str) -> None:
    out = tmp_path / "service.json"
    args = ["--device", "cpu", "--data", str(no_data), "--phantom", PHANTOM, "--repeat", "1", "--baseline"]
    args += ["--redis-server", redis_executable, "--timeout", "120", "--workdir", str(tmp_path / "work")]
    args += ["--predecode-anchor"]  # issue 46 item 4: the same input without decoding during the upload
    args += ["--predecode-min-bytes", "0"]  # the tiny phantom decoded during its upload too
    run_module("service", [*args, "--out", str(out)], tmp_path)
    report = load(out)
    has_keys(report, "benchmark", "device", "host", "timing", "preparation", "results", "warmup", "baseline")
    assert "error" not in report["warmup"] and "error" not in report["baseline"]["warmup"]
    assert list(report["results"]) == [NAME]
    r = report["results"][NAME]
    for summary in (r, r["baseline"]):
        assert summary.get("failed_runs") == [], summary
        assert finite(summary["upload_to_links_seconds"]) and summary["median_run"]["mesh_faces"] > 0
    assert finite(r["baseline_over_new"])
    assert r["median_run"]["decoded_during_upload"] is True and "load" in r["median_run"]["worker_seconds"]
    api = r["median_run"]["api_upload_seconds"]  # the API's own line: each step of the upload, the decoder's end too
    assert {"open", "body", "commit", "inspect", "decoder", "record", "total"} <= set(api)
    assert sum(v for k, v in api.items() if k != "total") == pytest.approx(api["total"], abs=0.01)
    anchor = r["predecode_anchor"]
    assert anchor.get("failed_runs") == [] and anchor["median_run"]["decoded_during_upload"] is False
    effect = r["predecode_effect"]["loading_seconds_worker"]
    assert finite(effect["with"]) and finite(effect["without"])


def test_throughput(tmp_path: Path, redis_executable: str) -> None:
    from engine.device import init_runtime

    init_runtime(os.environ.get("WARP_CACHE_PATH"))
    import warp as wp

    # the kernel cache the suite's workers fill (Warp keeps it in a folder named after its version): a fresh one
    # would cost a CPU compilation of every kernel in the warm-up
    cache = Path(str(wp.config.kernel_cache_dir))
    cache = cache.parent if cache.name == wp.config.version else cache
    out = tmp_path / "throughput.json"
    args = ["--devices", "cpu,cpu", "--jobs", "2", "--phantom", PHANTOM, "--uploaders", "2", "--api-workers", "1"]
    args += ["--mode", "both", "--cpu-layout", "halves"]  # uploading, then queued (workers paused while uploading)
    args += ["--rounds", "2"]  # the second round: all workers first, then one
    args += ["--upload-processes"]  # each client a process of its own
    args += ["--redis-server", redis_executable, "--warp-cache", str(cache), "--workdir", str(tmp_path / "work")]
    run_module("throughput", [*args, "--out", str(out)], tmp_path)
    report = load(out)
    has_keys(report, "benchmark", "machine", "host", "input", "timing", "warmup", "one_worker", "all_workers")
    phases = (("one_worker", 1), ("all_workers", 2), ("queued_one_worker", 1), ("queued_all_workers", 2))
    (second,) = report["more_rounds"]
    for key, workers, phase in [*((k, n, report[k]) for k, n in phases), *((k, n, second[k]) for k, n in phases)]:
        assert phase["workers"] == workers and phase["jobs"] == 2 and phase["upload_processes"] is True, key
        assert phase["queued"] is key.startswith("queued_") and finite(phase["uploads_seconds"]), key
        assert finite(phase["seconds"]) and finite(phase["jobs_per_minute"]), key
        assert 0 <= phase["first_start_seconds"] <= phase["seconds"], key
        if not phase["queued"]:  # queued: the uploads were done before the phase's clock started
            assert 0 < phase["last_upload_done_seconds"] <= phase["client_seconds"], key
        else:
            assert phase["last_upload_done_seconds"] <= 0 < phase["uploads_seconds"], key
        rows = phase["jobs_detail"]  # one per job, each with the worker's timing line (worker.tasks) parsed
        assert len(rows) == 2 and {r["worker"] for r in rows} <= set(range(workers)), rows
        for row in rows:
            steps = row["timings"]
            assert {"claim", "load", "reconstruct", "write_files", "publish", "finish", "total"} <= set(steps), row
            assert all(finite(v) and v >= 0 for v in steps.values()), row
            assert sum(v for k, v in steps.items() if k not in ("total", "queue_wait")) <= steps["total"] + 1e-3, row
            assert finite(row["upload_seconds"]) and "pipeline.isosurface" in row["engine"], row
        medians = phase["stage_medians"]
        assert finite(medians["reconstruct"]) and finite(medians["upload"]) and finite(medians["queue_wait"]), key
        assert finite(medians["api.body"]) and finite(medians["api.total"]), key  # the API's own line per upload
        assert len(phase["load_average_at_end"]) == 3, key
        if workers == 1:  # two jobs: the rate after the first is 60 / the time between their finishes
            ends = sorted(r["finished_at"] for r in rows)
            assert abs(phase["after_first_jobs_per_minute"] - 60 / (ends[1] - ends[0])) < 1e-6, key
        else:  # one job each: no rate after a first
            assert phase["after_first_jobs_per_minute"] is None, key
    assert finite(report["speedup"]) and finite(report["queued_speedup"])
    for prefix in ("", "queued_"):  # one ratio per round, the first also on its own; their median
        ratios = report[f"{prefix}speedups"]
        assert len(ratios) == 2 and ratios[0] == report[f"{prefix}speedup"] and all(finite(r) for r in ratios)
        assert min(ratios) <= report[f"{prefix}median_speedup"] <= max(ratios)
    jobs = tmp_path / "work" / "stack" / "data" / "jobs"  # each phase's jobs were deleted once measured
    assert jobs.is_dir() and not any(jobs.iterdir()), list(jobs.iterdir())
    z, y, x = (int(v) for v in PHANTOM.split(","))  # the workers page-lock for the phantom (on CUDA only)
    assert report["warmup_volume_bytes"] == str(2 * z * y * x) and report["workers_warm_up"] == "auto"


def test_defect_quality(tmp_path: Path) -> None:
    from benchmarks.defect_quality import main

    out = tmp_path / "defect_quality.json"
    assert main(["--device", "cpu", "--scans", "headsq", "--sizes", "30", "--out", str(out)]) == 0
    report = load(out)
    has_keys(report, "device", "summary", "rows")
    assert report["rows"] and all(r["scan"] == "headsq" for r in report["rows"])
    assert all(finite(r["seconds"]) for r in report["rows"] if "seconds" in r)


def test_defect_speed(tmp_path: Path) -> None:
    from benchmarks.defect_speed import main
    from tests.conftest import shared_file

    cranium = shared_file("cranium_ct", "cranium_ct_png16.zip")
    out = tmp_path / "defect_speed.json"
    assert main(["--device", "cpu", "--data", str(cranium), "--repeat", "1", "--out", str(out)]) == 0
    text = out.read_text()
    assert text.strip().startswith("{") and "NaN" not in text


def test_storage_clients(tmp_path: Path) -> None:
    out = tmp_path / "storage_clients.json"
    args = ["--sizes-mib", "9", "--repeat", "1", "--outputs", "2", "--output-mib", "1", "--signs", "4"]
    run_module("storage_clients", [*args, "--out", str(out)], tmp_path)
    report = load(out)
    has_keys(report, "benchmark", "store", "versions", "machine", "args", "results")
    assert sorted(r["client"] for r in report["results"]) == ["boto3", "obstore"]
    for r in report["results"]:
        assert r["size_mib"] == 9, r
        for key in ("upload_s", "download_s", "publish_s", "sign_s", "client_s", "upload_mib_s", "sign_us_each"):
            assert finite(r[key]) and r[key] > 0, (key, r)


def test_cpu_contention(tmp_path: Path) -> None:
    out = tmp_path / "cpu_contention.json"
    run_module("cpu_contention", ["--seconds", "0.05", "--out", str(out)], tmp_path)
    report = load(out)
    has_keys(report, "benchmark", "host", "solo_calls_per_second", "pair_with_first", "pools")
    assert finite(report["solo_calls_per_second"]) and report["pair_with_first"], report
    assert all(finite(v) and v > 0 for v in report["pair_with_first"].values()), report
    for name, runs in report["pools"].items():
        assert len(runs["alone"]) == 1 and len(runs["together"]) == 2, name
        assert all(r["calls_per_second"] > 0 for r in runs["alone"] + runs["together"]), name


def test_load_contention(tmp_path: Path) -> None:
    out = tmp_path / "load_contention.json"
    run_module(
        "load_contention",
        ["--phantom", "8,32,32", "--loads", "1", "--unfilter", "host,device", "--gpus", "cpu,cpu", "--out", str(out)],
        tmp_path,
    )
    report = load(out)
    has_keys(report, "benchmark", "host", "input", "fresh_alone", "fresh_both", "reused_alone", "reused_both")
    for key in ("fresh", "reused", "device_fresh", "device_reused"):  # "device" on the CPU: the host path, labelled
        assert len(report[f"{key}_alone"]) == 1 and len(report[f"{key}_both"]) == 2, key
        for proc in report[f"{key}_alone"] + report[f"{key}_both"]:
            (row,) = proc["loads"]
            assert finite(row["seconds"]) and row["seconds"] > 0 and row["user"] >= 0 and row["sys"] >= 0, row


def test_png_rows(tmp_path: Path) -> None:
    out = tmp_path / "png_rows.json"
    run_module(
        "png_rows",
        ["--phantom", "8,24,32", "--device", "cpu", "--slab-mb", "1", "--loads", "1", "--out", str(out)],
        tmp_path,
    )
    report = load(out)
    has_keys(report, "benchmark", "device", "threads", "stacks")
    for name in ("pillow", "paeth"):
        stack = report["stacks"][name]
        assert stack["device_1mb"]["equal_to_host"] is True, name
        assert finite(stack["host"]["median_seconds"]) and finite(stack["device_only"]["median_seconds"]), name
    assert report["stacks"]["paeth"]["zip"]["filter_share"][4] == 1.0


def test_first_load(tmp_path: Path) -> None:
    out = tmp_path / "first_load.json"
    args = ["--phantom", "8,24,32", "--device", "cpu", "--loads", "2", "--reserve", "0,scan", "--threads", "2"]
    run_module("first_load", [*args, "--workdir", str(tmp_path / "work"), "--out", str(out)], tmp_path)
    report = load(out)
    has_keys(report, "benchmark", "host", "device", "input", "runs")
    assert [r["reserve_bytes"] for r in report["runs"]] == [0, 2 * 8 * 24 * 32]
    for run in report["runs"]:  # a new process each: its warm-up, then the loads
        assert run["warm_up"]["device"] == "cpu" and run["warm_up"]["pinned_bytes"] == 0  # nothing page-locked off CUDA
        assert len(run["loads"]) == 2 and all(finite(x["seconds"]) and x["cpu_seconds"] >= 0 for x in run["loads"])


def test_big_formats(tmp_path: Path) -> None:
    from benchmarks.big_formats import FORMATS

    out = tmp_path / "big_formats.json"
    args = ["--shape", PHANTOM, "--chunks", "4,16,16", "--threads", "2", "--out", str(out)]
    run_module("big_formats", args, tmp_path)
    report = load(out)
    has_keys(report, "benchmark", "host", "shape_zyx", "dtype", "volume_bytes", "formats")
    assert report["volume_bytes"] == 2 * 16 * 32 * 32 and list(report["formats"]) == list(FORMATS)
    for name, row in report["formats"].items():
        assert "error" not in row and row["equal"] is True, (name, row)
        assert row["peak_rss_bytes"] >= row["baseline_rss_bytes"] > 0 and finite(row["ratio"]), (name, row)
        assert finite(row["seconds"]), (name, row)
    assert report["formats"]["ome-zarr-s3"]["source"]["container"] == "s3"
    assert report["formats"]["ome-zarr-v05"]["source"]["spacing_from"] == "ome-zarr"
