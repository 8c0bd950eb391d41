"""Write the JSON Schema of every message to schemas/json/<kind>.json, for clients in other languages.

python -m occvo_schemas.export            # write
python -m occvo_schemas.export --check    # exit 1 when the files drift from the models
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from occvo_schemas.models import MESSAGES, SCHEMA_VERSION

JSON_DIR = Path(__file__).parent / "json"


def rendered() -> dict[str, str]:
    out = {}
    for kind, model in sorted(MESSAGES.items()):
        schema = model.model_json_schema(mode="validation")
        schema["$id"] = f"occvo/{kind}/v{SCHEMA_VERSION}"
        schema["x-msgpack"] = "bytes fields are msgpack bin; Array.data is C-order little-endian"
        out[f"{kind}.json"] = json.dumps(schema, indent=2, sort_keys=True) + "\n"
    return out


def drift(directory: Path = JSON_DIR) -> list[str]:
    """Names of files that are missing, stale or unexpected."""
    want = rendered()
    have = {p.name: p.read_text() for p in directory.glob("*.json")} if directory.is_dir() else {}
    return sorted(n for n in set(want) | set(have) if want.get(n) != have.get(n))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true")
    args = parser.parse_args(argv)
    if args.check:
        stale = drift()
        if stale:
            print("schemas/json drifted from the models: " + ", ".join(stale) + " (run python -m occvo_schemas.export)")
            return 1
        return 0
    JSON_DIR.mkdir(exist_ok=True)
    for old in JSON_DIR.glob("*.json"):
        old.unlink()
    for name, text in rendered().items():
        (JSON_DIR / name).write_text(text)
    print(f"wrote {len(MESSAGES)} schemas to {JSON_DIR}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
