"""The ``bonemesh`` command: ``serve`` (the API) and ``worker`` (a Celery worker) here; every other command
(``reconstruct``, ``isosurface``, ``sweep``) is the engine's (:mod:`engine.cli`).

    bonemesh serve [--host 127.0.0.1] [--port 8000] [--workers 1]
    bonemesh worker [--loglevel INFO] [--device auto|cpu|cuda:N]
    bonemesh pacs [--host H] [--port P] [--ae-title AE]   (service.pacs.gateway)

Both read their settings from ``BONEMESH_*`` environment variables (:mod:`service.settings`).
"""

from __future__ import annotations

import argparse
import os
import sys


def _serve(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="bonemesh serve", description="Start the bonemesh API (uvicorn).")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--log-level", default="info")
    parser.add_argument(
        "--workers",
        type=int,
        default=1,
        help="API processes sharing the port: each parses the uploads it receives, so several take uploads in "
        "parallel (they share the data folder's signing key and database)",
    )
    args = parser.parse_args(argv)
    if args.workers < 1:
        parser.error("--workers must be at least 1")
    import uvicorn

    uvicorn.run(
        "service.app:create_app",
        factory=True,
        host=args.host,
        port=args.port,
        log_level=args.log_level,
        workers=args.workers if args.workers > 1 else None,
    )
    return 0


def _worker(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="bonemesh worker", description="Start a Celery worker: one job at a time (run one per GPU)."
    )
    parser.add_argument("--loglevel", default="INFO")
    parser.add_argument("--device", help="auto, cpu or cuda:N (default BONEMESH_DEVICE, else auto)")
    parser.add_argument("--hostname", help="Celery node name (default bonemesh@<host>-<pid>)")
    parser.add_argument(
        "--max-device-bytes", help="device memory budget per job, e.g. 8GiB (default BONEMESH_MAX_DEVICE_BYTES)"
    )
    args = parser.parse_args(argv)
    if args.device:
        os.environ["BONEMESH_DEVICE"] = args.device
    if args.max_device_bytes:
        from engine.memory import parse_bytes

        try:
            parse_bytes(args.max_device_bytes)
        except ValueError as exc:
            parser.error(str(exc))
        os.environ["BONEMESH_MAX_DEVICE_BYTES"] = args.max_device_bytes
    from service.settings import get_settings

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


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "serve":
        return _serve(argv[1:])
    if argv and argv[0] == "worker":
        return _worker(argv[1:])
    if argv and argv[0] == "pacs":
        from service.pacs.gateway import main as pacs_main

        return pacs_main(argv[1:])
    from engine.cli import main as engine_main

    if not argv or argv[0] in ("-h", "--help"):
        print("bonemesh serve | worker | pacs: the service, its worker, the PACS node (see bonemesh serve --help)")  # noqa: T201
    return engine_main(argv)


if __name__ == "__main__":
    sys.exit(main())
