"""occvo map-info: bounds, tile count and size of a stream's map."""

from __future__ import annotations

import json

from services.client import OccVOClient, ServiceError
from services.commands._common import add_connection, endpoint


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("map-info", help="map bounds, tile count and size")
    add_connection(p)
    p.set_defaults(func=run)


def run(args) -> int:
    with OccVOClient(endpoint(args), stream=args.stream) as client:
        try:
            info = client.map_info()
        except ServiceError as exc:
            print(json.dumps({"error": str(exc)}))
            return 1
    print(json.dumps(info.model_dump(exclude={"kind", "schema_version"})))
    return 0
