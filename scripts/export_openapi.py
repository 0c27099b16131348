#!/usr/bin/env python3
"""Write the REST API's OpenAPI spec to openapi/openapi.json (or the path given).

The spec is generated from the app itself (`create_app(MapRegistry())`: no worker runs, nothing
listens), with sorted keys and an indent of 2 so diffs stay readable. The committed file must match
what this writes: tests/test_api_openapi.py fails otherwise. Run it after changing the API:

    .venv/bin/python scripts/export_openapi.py
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from fleetmap.api import create_app
from fleetmap.registry import MapRegistry

DEFAULT_PATH = Path(__file__).resolve().parents[1] / "openapi" / "openapi.json"


def spec_text() -> str:
    """The spec as the exact text committed to openapi/openapi.json."""
    spec = create_app(MapRegistry()).openapi()
    return json.dumps(spec, indent=2, sort_keys=True, ensure_ascii=False, allow_nan=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", type=Path, default=DEFAULT_PATH, help=f"default {DEFAULT_PATH}")
    args = parser.parse_args(argv)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(spec_text(), encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
