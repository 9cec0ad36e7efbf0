# bonemesh: one image for the API (`bonemesh serve`) and the worker (`bonemesh worker`).
#
#   docker build -t bonemesh .
#   docker compose up                     # redis + api + GPU worker (NVIDIA container runtime)
#   docker compose --profile cpu up redis api worker-cpu
#   docker build --build-arg BONEMESH_OPENCL=1 -t bonemesh .   # + the OpenCL backend: PoCL (every CPU core) and
#                                         # the ICD loader; GPU vendors' OpenCL drivers come from the host
#
# Warp's wheels carry their CUDA runtime, so a slim Python base is enough: the NVIDIA runtime only has to mount
# the driver (compose asks for it with a device reservation). MeshLab (decimation) needs libGL / libOpenGL.
# the page's browser assets (model-viewer, three.js decoders, QR code) from the npm registry, pinned by the lock file
FROM node:20-slim AS assets
WORKDIR /assets
COPY package.json package-lock.json ./
RUN npm ci --omit=dev --ignore-scripts --no-audit --no-fund

FROM python:3.11-slim
ARG BONEMESH_OPENCL=0

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    BONEMESH_DATA_DIR=/data \
    WARP_CACHE_PATH=/var/cache/warp \
    BONEMESH_ASSETS_DIR=/app/node_modules

RUN apt-get update \
    && apt-get install -y --no-install-recommends libgl1 libopengl0 libgomp1 \
    && if [ "$BONEMESH_OPENCL" = 1 ]; then apt-get install -y --no-install-recommends pocl-opencl-icd ocl-icd-libopencl1; fi \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app
# dependencies first (a layer that survives source edits), then the source
COPY pyproject.toml README.md ./
COPY engine ./engine
COPY core ./core
COPY service ./service
COPY worker ./worker
COPY docker/worker-entry.sh /usr/local/bin/bonemesh-worker-entry
COPY --from=assets /assets/node_modules ./node_modules
# pacs: the PACS gateway; postgres: psycopg, for BONEMESH_DATABASE_URL=postgresql+psycopg://...; s3: boto3, for
# BONEMESH_STORAGE_URL=s3://...; opencl (build argument): pyopencl, for BONEMESH_DEVICE=opencl
RUN pip install ".[pacs,postgres,s3$( [ "$BONEMESH_OPENCL" = 1 ] && echo ,opencl )]" \
    && useradd --system --uid 10001 --home-dir /data bonemesh \
    && mkdir -p /data /var/cache/warp /run/bonemesh-gpus \
    && chown bonemesh /data /var/cache/warp /run/bonemesh-gpus

USER bonemesh
VOLUME ["/data"]
EXPOSE 8000
CMD ["bonemesh", "serve", "--host", "0.0.0.0", "--port", "8000"]
