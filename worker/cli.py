"""``bonemesh worker``: start a Celery worker of the ``bonemesh`` queue, one job at a time (run one per GPU).

    bonemesh worker [--loglevel INFO] [--device auto|cpu|cuda:N] [--hostname NODE] [--max-device-bytes 8GiB]

Reached through the ``bonemesh`` console script (:mod:`service.cli` looks this module up only for ``worker``);
settings come from ``BONEMESH_*`` environment variables (:mod:`core.settings`). Importing it never imports Warp.
"""

from __future__ import annotations

import argparse
import os
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="bonemesh worker", description="Start a Celery worker: one job at a time (run one per GPU)."
    )
    parser.add_argument("--loglevel", default="INFO")
    parser.add_argument("--device", help="auto, cpu or cuda:N (default BONEMESH_DEVICE, else auto)")
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


if __name__ == "__main__":
    sys.exit(main())
