# bonemesh: one image for the API (`bonemesh serve`) and the worker (`bonemesh worker`).
#
#   docker build -t bonemesh .
#   docker compose up                     # redis + api + GPU worker (NVIDIA container runtime)
#   docker compose --profile cpu up redis api worker-cpu
#
# Warp's wheels carry their CUDA runtime, so a slim Python base is enough: the NVIDIA runtime only has to mount
# the driver (compose asks for it with a device reservation). MeshLab (decimation) needs libGL / libOpenGL.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    BONEMESH_DATA_DIR=/data \
    WARP_CACHE_PATH=/var/cache/warp

RUN apt-get update \
    && apt-get install -y --no-install-recommends libgl1 libopengl0 libgomp1 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app
# dependencies first (a layer that survives source edits), then the source
COPY pyproject.toml README.md ./
COPY engine ./engine
COPY service ./service
COPY worker ./worker
RUN pip install ".[pacs]" \
    && useradd --system --uid 10001 --home-dir /data bonemesh \
    && mkdir -p /data /var/cache/warp \
    && chown bonemesh /data /var/cache/warp

USER bonemesh
VOLUME ["/data"]
EXPOSE 8000
CMD ["bonemesh", "serve", "--host", "0.0.0.0", "--port", "8000"]
