"""``python -m engine`` runs the command line."""

import sys

if __name__ == "__main__":
    try:
        from engine.cli import main
    except KeyboardInterrupt:  # Ctrl-C while the modules load: one line, as in main
        print("bonemesh: interrupted", file=sys.stderr)  # noqa: T201
        raise SystemExit(130) from None
    raise SystemExit(main())
