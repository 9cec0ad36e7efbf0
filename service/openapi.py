"""Export the API's OpenAPI document: ``python -m service.openapi`` writes ``openapi/openapi.json``;
``--check`` exits 1 when the committed file differs from the app's (a test runs the same comparison)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

DEFAULT = Path(__file__).resolve().parents[1] / "openapi" / "openapi.json"


def render() -> str:
    """The app's OpenAPI document as stable, indented JSON."""
    from core.settings import Settings
    from service.app import create_app

    app = create_app(Settings(api_keys=["openapi-export"], secret_key="openapi-export"))
    return json.dumps(app.openapi(), indent=2, sort_keys=True) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=DEFAULT)
    parser.add_argument("--check", action="store_true", help="compare instead of writing")
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        if not args.out.exists() or args.out.read_text() != text:
            print(f"{args.out} is out of date: run python -m service.openapi", file=sys.stderr)  # noqa: T201
            return 1
        return 0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
