#!/bin/sh
# Container entry of a bonemesh worker: one GPU per worker, however many replicas run.
#
# Every GPU worker container sees all of the host's GPUs (compose: `count: all`) and claims the first one no other
# worker holds, with a lock file per GPU on a volume the workers share (BONEMESH_GPU_LOCKS). The lock is held by
# an open file descriptor that the worker inherits through `exec`, so it is released when the worker's container
# stops or dies, and a restarted or added replica takes the GPU that is free. The claimed GPU is the only one the
# worker sees (CUDA_VISIBLE_DEVICES), as cuda:0, with a Warp kernel cache of its own.
#
# BONEMESH_DEVICE=cpu (the CPU worker) and opencl[:N] (the OpenCL worker: a GPU's OpenCL driver or PoCL on the
# CPU, engine.backend) claim no NVIDIA GPU and start without one. BONEMESH_GPUS overrides the GPU count (default:
# the /dev/nvidiaN device nodes the NVIDIA runtime mounted). The Celery node name is bonemesh@<container hostname>,
# which the compose health check pings.
set -eu
node="bonemesh@$(hostname)"
case "${BONEMESH_DEVICE:-auto}" in
  cpu | opencl | opencl:*)
    exec bonemesh worker --hostname "$node" "$@" ;;
esac
locks="${BONEMESH_GPU_LOCKS:-/run/bonemesh-gpus}"
mkdir -p "$locks"
gpus="${BONEMESH_GPUS:-$(ls /dev/nvidia[0-9]* 2>/dev/null | wc -l)}"
if [ "$gpus" -eq 0 ]; then
  echo "bonemesh worker $node: no NVIDIA GPU in this container (no /dev/nvidiaN: is the NVIDIA container runtime" \
    "installed and the GPU reserved?); without a GPU run the worker-cpu or worker-opencl service" >&2
  exit 1
fi
i=0
while [ "$i" -lt "$gpus" ]; do
  exec 9>>"$locks/gpu$i.lock"
  if flock -n 9; then
    echo "bonemesh worker $node: GPU $i of $gpus" >&2
    export CUDA_DEVICE_ORDER=PCI_BUS_ID CUDA_VISIBLE_DEVICES="$i" BONEMESH_DEVICE=cuda:0
    export WARP_CACHE_PATH="${WARP_CACHE_PATH:-/var/cache/warp}/gpu$i"
    exec bonemesh worker --hostname "$node" "$@"
  fi
  exec 9>&-
  i=$((i + 1))
done
echo "bonemesh worker $node: all $gpus GPU(s) are taken by other workers; run at most one worker per GPU" >&2
exit 1
