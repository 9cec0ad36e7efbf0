"""The ``bonemesh`` command: ``serve`` (the API) here, ``worker`` (a Celery worker) in :mod:`worker.cli`, ``pacs``
in :mod:`service.pacs.gateway`; every other command (``reconstruct``, ``isosurface``, ``sweep``) is the engine's
(:mod:`engine.cli`). Each is imported only when its command runs, so ``bonemesh serve`` never imports the worker.

    bonemesh serve [--host 127.0.0.1] [--port 8000] [--workers 1]
    bonemesh worker [--loglevel INFO] [--device auto|cpu|cuda:N]   (worker.cli)
    bonemesh pacs [--host H] [--port P] [--ae-title AE]   (service.pacs.gateway)

Each reads its settings from ``BONEMESH_*`` environment variables (:mod:`core.settings`). ``bonemesh --help`` lists
every command (the service's and the engine's, read from the engine's own parser); ``bonemesh --version`` prints the
installed version.
"""

from __future__ import annotations

import argparse
import copy
import sys
from typing import Any

# the service's commands, listed by `bonemesh --help` before the engine's
SERVICE_COMMANDS = {
    "serve": "start the API (uvicorn): the web page and the HTTP API",
    "worker": "start a worker: one job at a time (run one per GPU)",
    "pacs": "start the DICOM node: CT series from a PACS in, models back (the pacs extra)",
}


def version() -> str:
    """The installed distribution's version (``bonemesh --version``)."""
    import importlib.metadata as md

    try:
        return md.version("bonemesh")
    except md.PackageNotFoundError:  # a source tree that was never installed
        return "unknown (not installed)"


def engine_commands(engine_cli: Any) -> dict[str, str]:
    """{name: help} of the engine's subcommands, read from its parser (``engine.cli.build_parser``)."""
    build = getattr(engine_cli, "build_parser", None)
    if build is None:
        return {}
    parser = build()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            return {name: helps.get(name, "") for name in action.choices}
    return {}


def help_text(engine_cli: Any) -> str:
    """``bonemesh --help``: usage, then every command with its one line."""
    commands = {**SERVICE_COMMANDS, **engine_commands(engine_cli)}
    width = max(len(name) for name in commands) + 2
    lines = [
        "usage: bonemesh [-h] [--version] COMMAND ...",
        "",
        "Bone surface models from CT and micro-CT slice stacks: the service (API, worker, PACS node) and the",
        "engine's commands.",
        "",
        "commands:",
        *(f"  {name:<{width}}{text}" for name, text in commands.items()),
        "",
        "options:",
        f"  {'-h, --help':<{width}}show this help and exit",
        f"  {'--version':<{width}}print the version and exit",
        "",
        "`bonemesh COMMAND --help` shows a command's options.",
    ]
    return "\n".join(lines) + "\n"


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
        log_config=log_config(args.log_level),
        workers=args.workers if args.workers > 1 else None,
    )
    return 0


def log_config(level: str) -> dict[str, Any]:
    """uvicorn's own logging, with the API's loggers (``bonemesh.*``: uploads, decoders, the background sweeps)
    written beside uvicorn's lines at ``level``. Without it only their warnings reach the log, and bare."""
    from uvicorn.config import LOGGING_CONFIG

    config = copy.deepcopy(LOGGING_CONFIG)
    config["loggers"]["bonemesh"] = {"handlers": ["default"], "level": level.upper(), "propagate": False}
    return config


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--version":
        print(f"bonemesh {version()}")  # noqa: T201
        return 0
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
        import engine.cli

        # no command: the same list on stderr, and the usage error's status
        print(help_text(engine.cli), end="", file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    return engine_main(argv)


if __name__ == "__main__":
    sys.exit(main())
