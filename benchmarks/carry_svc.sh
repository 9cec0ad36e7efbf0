#!/usr/bin/env bash
# Builds .gpu/svc (ignored by git, under 55 MB): what benchmarks/service.py and benchmarks/throughput.py need on
# the GPU machine beyond the engine's wheels, which has no package registry and no redis-server:
#   whl/          the service's wheels for CPython 3.12 on manylinux x86_64 (the versions of this checkout's .venv,
#                 with the dependencies pip resolves for them)
#   redis/        redis-server with every library ldd lists for it, glibc and its loader included, started through
#                 redis.sh, which hands the bundled loader the bundled folder (its LD_LIBRARY_PATH)
#   data/         the cranium scan (with its licence) for benchmarks/service.py --data .gpu/svc/data
#   install_svc.sh  run there after the engine's install: installs the wheels into /tmp/site, checks the imports
# Run from the repository root, after ../shared/gpu/prepare (which empties .gpu). See docs/benchmarks.md.
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
py=${PYTHON:-.venv/bin/python}
out=.gpu/svc
rm -rf "$out"
mkdir -p "$out/whl" "$out/redis/lib" "$out/data/cranium_ct"

# the service side of pyproject's dependencies (the engine's wheels come from ../shared/gpu/prepare), pinned to
# what this checkout's tests ran with; pip resolves their own dependencies for the GPU machine's Python
top='fastapi|fastapi[-_]offline|uvicorn|uvloop|httptools|python-multipart|pydantic|pydantic-settings|sqlalchemy|celery|redis|httpx'
mapfile -t pins < <("$py" -m pip freeze | grep -iE "^($top)==")
[ "${#pins[@]}" -ge 12 ] || { echo "expected 12 pinned packages in $py's environment, got: ${pins[*]}" >&2; exit 2; }
python3 -m pip download -q --only-binary=:all: --python-version 3.12 --implementation cp --abi cp312 \
  --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux_2_28_x86_64 \
  -d "$out/whl" "${pins[@]}" 2>&1 | grep -v "is ignored" || true
ls "$out"/whl/*.whl >/dev/null

redis=$(readlink -f "$(command -v redis-server)")
cp "$redis" "$out/redis/redis-server"
ldd "$redis" | awk '/=>/ {print $3} /ld-linux/ {print $1}' | sort -u | while read -r lib; do
  cp -L "$lib" "$out/redis/lib/"
done
cat > "$out/redis/redis.sh" <<'EOF'
#!/bin/sh
# redis-server with the libraries it was built against (glibc and its loader included): runs on any x86_64 Linux
here=$(cd "$(dirname "$0")" && pwd)
export LD_LIBRARY_PATH="$here/lib"
exec "$here/lib/ld-linux-x86-64.so.2" --library-path "$here/lib" "$here/redis-server" "$@"
EOF
chmod +x "$out/redis/redis.sh" "$out/redis/redis-server"

data=${BONEMESH_SHARED_DATA:-../shared/data}
cp "$data"/cranium_ct/{cranium_ct_png16.zip,README.md,LICENSE-GPL-2.txt,COPYRIGHT-debian-invesalius-examples.txt} \
  "$out/data/cranium_ct/"

cat > "$out/install_svc.sh" <<'EOF'
#!/usr/bin/env bash
# On the GPU machine, from the repository root, after the engine's wheels are in /tmp/site: the service's wheels
# into /tmp/site (replacing older copies of shared pure-Python dependencies such as typing_extensions or packaging,
# at the versions the tests ran with), redis-server made runnable, and the imports checked.
# PY and SITE name another interpreter and target (a rehearsal on another machine).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
PY=${PY:-python3}
SITE=${SITE:-/tmp/site}
"$PY" -m pip install -q --no-index --no-deps --no-compile --upgrade --target "$SITE" "$here"/whl/*.whl
chmod +x "$here/redis/redis.sh" "$here/redis/redis-server" "$here"/redis/lib/*
"$here/redis/redis.sh" --version
PYTHONPATH=$SITE:$PWD "$PY" - <<'PY'
import importlib
for name in ("fastapi", "fastapi_offline", "starlette", "uvicorn", "uvloop", "httptools", "python_multipart",
             "pydantic", "pydantic_settings", "sqlalchemy", "celery", "kombu", "billiard", "redis", "httpx",
             "service.app", "worker.tasks", "engine.io", "engine.job.pipeline", "engine.job.outputs"):
    importlib.import_module(name)
print("service, worker and engine import")
PY
EOF
chmod +x "$out/install_svc.sh"
du -sh "$out" "$out"/*
