"""The ``bonemesh`` command: ``serve`` (the API) here, ``worker`` (a Celery worker) in :mod:`worker.cli`, ``pacs``
in :mod:`service.pacs.gateway`; every other command (``reconstruct``, ``isosurface``, ``sweep``) is the engine's
(:mod:`engine.cli`). Each is imported only when its command runs, so ``bonemesh serve`` never imports the worker.

    bonemesh serve [--host 127.0.0.1] [--port 8000] [--workers 1]
    bonemesh worker [--loglevel INFO] [--device auto|cpu|cuda:N]   (worker.cli)
    bonemesh pacs [--host H] [--port P] [--ae-title AE]   (service.pacs.gateway)

Each reads its settings from ``BONEMESH_*`` environment variables (:mod:`core.settings`).
"""

from __future__ import annotations

import argparse
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


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "serve":
        return _serve(argv[1:])
    if argv and argv[0] == "worker":
        # the one edge from the API package to the worker: a console-script dispatch, looked up only when
        # `bonemesh worker` runs (tests/test_import_contracts.py allows exactly this one)
        from worker.cli import main as worker_main

        return worker_main(argv[1:])
    if argv and argv[0] == "pacs":
        from service.pacs.gateway import main as pacs_main

        return pacs_main(argv[1:])
    try:
        from engine.cli import main as engine_main
    except KeyboardInterrupt:  # Ctrl-C while the engine loads: one line, as engine.cli.main says it later
        print("bonemesh: interrupted", file=sys.stderr)  # noqa: T201
        return 130

    if not argv or argv[0] in ("-h", "--help"):
        print("bonemesh serve | worker | pacs: the service, its worker, the PACS node (see bonemesh serve --help)")  # noqa: T201
    return engine_main(argv)


if __name__ == "__main__":
    sys.exit(main())
