"""occvo map-info: bounds, tile count and size of a stream's map."""

from __future__ import annotations

from occvo_services.commands._common import add_connection, add_json, client, emit


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("map-info", help="map bounds, tile count and size")
    add_connection(p)
    add_json(p)
    p.set_defaults(func=run)


def run(args) -> int:
    with client(args) as c:
        info = c.map_info()  # ServiceError (no map yet, no map service): one line, exit code 1
    record = info.model_dump(exclude={"kind", "schema_version"})
    emit(args, record, "\n".join(f"{k}: {v}" for k, v in record.items()))
    return 0
