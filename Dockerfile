# syntax=docker/dockerfile:1
# bonemesh: one image for the API (`bonemesh serve`) and the worker (`bonemesh worker`).
#
#   docker build -t bonemesh .
#   docker compose up                     # redis + api + GPU worker (NVIDIA container runtime)
#   docker compose --profile cpu up redis api worker-cpu
#   docker build --build-arg BONEMESH_OPENCL=1 -t bonemesh:opencl .   # + the OpenCL backend: PoCL (every CPU core)
#                                         # and the ICD loader; GPU vendors' OpenCL drivers come from the host
#   docker build --build-arg PYTHON_VERSION=3.13 -t bonemesh .          # 3.11 (default), 3.12 or 3.13
#
# Stages: `assets` (the page's npm packages), `wheels` (a compiler builds the one dependency published as source
# only, meshoptimizer, into a wheel) and the final image, which has no compiler: every other dependency installs
# from a wheel (tests/test_deploy.py resolves them for CPython 3.11-3.13 on manylinux x86_64), at the versions of
# constraints.txt (scripts/lock.py). Dependencies are installed before the source is copied, so a code edit
# rebuilds only the last layers.
#
# Warp's wheels carry their CUDA runtime, so a slim Python base is enough: the NVIDIA runtime only has to mount
# the driver (compose asks for it with a device reservation). MeshLab (the `reference` extra) is not in the image.
ARG PYTHON_VERSION=3.11

# the page's browser assets (model-viewer, three.js decoders, QR code) from the npm registry, pinned by the lock file
FROM node:24-slim AS assets
WORKDIR /assets
COPY package.json package-lock.json ./
RUN npm ci --omit=dev --ignore-scripts --no-audit --no-fund

# meshoptimizer (EXT_meshopt_compression's codecs) is an alpha published as a source distribution only: its wheel is
# built here, where the compiler is, and only the wheel goes on
FROM python:${PYTHON_VERSION}-slim AS wheels
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1
RUN apt-get update \
    && apt-get install -y --no-install-recommends build-essential \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /build
COPY constraints.txt ./
RUN pip wheel --no-deps --wheel-dir /wheels "$(grep '^meshoptimizer==' constraints.txt)"

FROM python:${PYTHON_VERSION}-slim
ARG BONEMESH_OPENCL=0
ARG BONEMESH_EXTRAS=pacs,postgres,s3

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    BONEMESH_DATA_DIR=/data \
    WARP_CACHE_PATH=/var/cache/warp \
    BONEMESH_ASSETS_DIR=/app/node_modules

RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 util-linux \
    && if [ "$BONEMESH_OPENCL" = 1 ]; then apt-get install -y --no-install-recommends pocl-opencl-icd ocl-icd-libopencl1; fi \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app
# dependencies first (a layer that survives source edits): the project's requirements and extras read from
# pyproject.toml, pinned by constraints.txt, wheels only (meshoptimizer's from the wheels stage). Extras: pacs (the
# PACS gateway), postgres (psycopg, BONEMESH_DATABASE_URL=postgresql+psycopg://...), s3 (boto3, BONEMESH_STORAGE_URL=s3://...),
# and with BONEMESH_OPENCL=1 opencl (pyopencl, BONEMESH_DEVICE=opencl)
COPY pyproject.toml constraints.txt ./
RUN --mount=type=bind,from=wheels,source=/wheels,target=/wheels \
    extras="$BONEMESH_EXTRAS$( [ "$BONEMESH_OPENCL" = 1 ] && echo ,opencl )" \
    && python -c "import sys, tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; \
print('\n'.join(p['dependencies'] + [r for e in sys.argv[1].split(',') if e for r in p['optional-dependencies'][e]]))" \
        "$extras" > /tmp/requirements.txt \
    && pip install --only-binary=:all: --find-links /wheels -c constraints.txt -r /tmp/requirements.txt \
    && rm /tmp/requirements.txt

# then the source: only these layers are rebuilt by a code edit
COPY README.md ./
COPY engine ./engine
COPY core ./core
COPY service ./service
COPY worker ./worker
RUN pip install --no-deps . \
    && useradd --system --uid 10001 --home-dir /data bonemesh \
    && mkdir -p /data /var/cache/warp /run/bonemesh-gpus \
    && chown bonemesh /data /var/cache/warp /run/bonemesh-gpus
COPY docker/worker-entry.sh /usr/local/bin/bonemesh-worker-entry
COPY --from=assets /assets/node_modules ./node_modules

USER bonemesh
VOLUME ["/data"]
EXPOSE 8000
CMD ["bonemesh", "serve", "--host", "0.0.0.0", "--port", "8000"]
