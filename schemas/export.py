"""Write the JSON Schema of every message to schemas/json/<kind>.json, for clients in other languages.

python -m occvo_schemas.export            # write
python -m occvo_schemas.export --check    # exit 1 when the files drift from the models

Earlier versions still on the wire (schemas/pose_v1.py) keep their schema under json/v<N>/<kind>.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from occvo_schemas.codec import schema_id
from occvo_schemas.models import MESSAGES
from occvo_schemas.pose_v1 import PoseEstimateV1

JSON_DIR = Path(__file__).parent / "json"


def _render(model, kind: str, version: int | None = None) -> str:
    schema = _bin_fields(model.model_json_schema(mode="validation"))
    schema["$id"] = schema_id(kind, version)
    schema["x-msgpack"] = "bytes fields are msgpack bin (x-msgpack-type); Array.data is C-order little-endian"
    return json.dumps(schema, indent=2, sort_keys=True) + "\n"


def rendered() -> dict[str, str]:
    return {f"{kind}.json": _render(model, kind) for kind, model in sorted(MESSAGES.items())}


def rendered_earlier() -> dict[str, str]:
    """The earlier versions still published, by path under json/."""
    return {"v1/pose_estimate.json": _render(PoseEstimateV1, "pose_estimate", 1)}


def _bin_fields(node):
    """pydantic writes a bytes field as a JSON string; on the wire it is msgpack bin, which a msgpack reader hands
    over as bytes, not text. Such a field says so (x-msgpack-type: bin) and names no JSON type, so a decoded payload
    validates as it arrives."""
    if isinstance(node, dict):
        if node.get("format") == "binary" and node.get("type") == "string":
            node = {k: v for k, v in node.items() if k not in ("type", "format")} | {"x-msgpack-type": "bin"}
        return {k: _bin_fields(v) for k, v in node.items()}
    if isinstance(node, list):
        return [_bin_fields(v) for v in node]
    return node


def drift(directory: Path = JSON_DIR) -> list[str]:
    """Names of files that are missing, stale or unexpected."""
    want = rendered()
    have = {p.name: p.read_text() for p in directory.glob("*.json")} if directory.is_dir() else {}
    return sorted(n for n in set(want) | set(have) if want.get(n) != have.get(n))


def drift_earlier(directory: Path = JSON_DIR) -> list[str]:
    return sorted(
        n
        for n, text in rendered_earlier().items()
        if not (directory / n).is_file() or (directory / n).read_text() != text
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true")
    args = parser.parse_args(argv)
    if args.check:
        stale = drift() + drift_earlier()
        if stale:
            print("schemas/json drifted from the models: " + ", ".join(stale) + " (run python -m occvo_schemas.export)")
            return 1
        return 0
    JSON_DIR.mkdir(exist_ok=True)
    for old in JSON_DIR.glob("*.json"):
        old.unlink()
    for name, text in (rendered() | rendered_earlier()).items():
        (JSON_DIR / name).parent.mkdir(exist_ok=True)
        (JSON_DIR / name).write_text(text)
    print(f"wrote {len(MESSAGES)} schemas to {JSON_DIR}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
