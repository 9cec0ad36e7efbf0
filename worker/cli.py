"""``bonemesh worker``: start a Celery worker of the ``bonemesh`` queue, one job at a time (run one per GPU).

    bonemesh worker [--loglevel INFO] [--device auto|cpu|cuda:N] [--hostname NODE] [--max-device-bytes 8GiB]

Reached through the ``bonemesh`` console script (:mod:`service.cli` looks this module up only for ``worker``);
settings come from ``BONEMESH_*`` environment variables (:mod:`core.settings`). Importing it never imports Warp.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="bonemesh worker", description="Start a Celery worker: one job at a time (run one per GPU)."
    )
    parser.add_argument("--loglevel", default="INFO")
    parser.add_argument(
        "--device",
        help="auto, cpu, cuda:N, opencl[:N], or several GPUs per job: cuda:0,cuda:1 or cuda:all "
        "(default BONEMESH_DEVICE, else auto)",
    )
    parser.add_argument("--hostname", help="Celery node name (default bonemesh@<host>-<pid>)")
    parser.add_argument(
        "--max-device-bytes", help="device memory budget per job, e.g. 8GiB (default BONEMESH_MAX_DEVICE_BYTES)"
    )
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.device:
        os.environ["BONEMESH_DEVICE"] = args.device
    if args.max_device_bytes:
        from engine.job import parse_bytes

        try:
            parse_bytes(args.max_device_bytes)
        except ValueError as exc:
            parser.error(str(exc))
        os.environ["BONEMESH_MAX_DEVICE_BYTES"] = args.max_device_bytes
    from core.settings import get_settings

    settings = get_settings()
    refused = _cuda_refusal(args.device or settings.device)
    if refused:
        sys.stderr.write(f"bonemesh worker: {refused}\n")
        return 2
    from worker.app import app

    node = args.hostname or f"bonemesh@%h-{os.getpid()}"
    app.worker_main(
        [
            "worker",
            "--pool=prefork",
            "--concurrency=1",
            "--prefetch-multiplier=1",
            f"--queues={settings.queue}",
            f"--loglevel={args.loglevel}",
            f"--hostname={node}",
            "--without-gossip",
            "--without-mingle",
        ]
    )
    return 0


def _cuda_refusal(device: str) -> str | None:
    """For a ``cuda[:N]`` worker whose GPU Warp cannot use, the one line saying why (the driver Warp needs and the
    one present, say): the worker does not start. For ``auto``, the same reason is written as a warning and the
    worker starts on what ``auto`` picks. The probe runs in a process of its own: CUDA initialised here, before
    the pool forks, would be unusable in the children."""
    if not (device == "auto" or device.startswith("cuda")):
        return None
    probe = [sys.executable, "-m", "engine.backend.warp_device"]
    try:
        done = subprocess.run(probe, capture_output=True, text=True, timeout=300, check=True)
        found = json.loads(done.stdout.strip().splitlines()[-1])
    except (subprocess.SubprocessError, OSError, ValueError, IndexError) as exc:
        return f"{device}: the CUDA probe failed ({exc})" if device != "auto" else None
    index = int(device.split(":")[1]) if ":" in device else 0
    if device == "auto":
        if found["nvidia_driver"] and found["why"]:
            sys.stderr.write(f"bonemesh worker: WARNING: auto does not use the GPU: {found['why']}\n")
        return None
    if found["cuda_devices"] > index:
        return None
    why = found["why"] or f"{found['cuda_devices']} CUDA device(s) present"
    return f"{device} is not usable: {why}"


if __name__ == "__main__":
    sys.exit(main())
