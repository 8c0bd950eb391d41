"""A client's gets: one query's decoded answers and error replies, asked again while it is answered only `busy`;
a region's tiles page by page."""

from __future__ import annotations

import time
from collections.abc import Callable

import zenoh

from occvo_schemas import keys
from occvo_schemas.codec import CodecError, decode, encode
from occvo_schemas.models import ErrorEvent, MapTile, MapTileQuery
from occvo_services.wire import encoding


def replies(
    session: zenoh.Session,
    source_info: Callable[[], zenoh.SourceInfo],
    stream: str,
    selector: str,
    expect,
    payload: bytes | None,
    timeout: float,
    first: bool = False,
) -> tuple[list, list[ErrorEvent]]:
    """The decoded answers and error replies of a get, within `timeout`. first: one answer is the whole answer (a
    tile, map info, a stream's trajectory or pose): taken as soon as it comes, so a queryable that never answers
    delays nothing. Answered only `busy` (this client has max_queries_per_client queries in work, e.g. from other
    threads), it is asked again after a short wait. source_info(): the info naming the asking client's session."""
    deadline, wait = time.monotonic() + timeout, 0.01
    while True:
        # the best match: one complete queryable (a map service replica) where there is one, else every match
        got = session.get(
            selector,
            payload=payload,
            timeout=max(0.01, deadline - time.monotonic()),
            target=zenoh.QueryTarget.BEST_MATCHING,
            consolidation=zenoh.ConsolidationMode.NONE,  # replies as they come; one per key kept by the caller
            source_info=source_info(),
            encoding=encoding("map_tile_query") if payload is not None else None,  # the one query with a payload
        )
        out, errs = _decoded(got, expect, stream, first)
        if out or not errs or any(e.code != "busy" for e in errs) or time.monotonic() + wait > deadline:
            return out, errs
        time.sleep(wait)
        wait = min(0.5, wait * 2)


def _decoded(got, expect, stream: str, first: bool) -> tuple[list, list[ErrorEvent]]:
    out, errs = [], []
    for reply in got:
        if reply.ok is not None:
            out.append(decode(reply.ok.payload.to_bytes(), expect, 1 << 30))
            if first:
                break
        else:
            try:
                errs.append(decode(reply.err.payload.to_bytes(), ErrorEvent))
            except CodecError:
                text = reply.err.payload.to_bytes().decode(errors="replace")
                errs.append(ErrorEvent(stream=stream, worker="?", code="internal", message=text))
    return out, errs


def region_tiles(ask, stream: str, ix_min, ix_max, iy_min, iy_max) -> tuple[list[MapTile], list[ErrorEvent]]:
    """The tiles of a region, page by page (the map service answers a page at a time; a "truncated" error says more
    follow), and the last page's errors. ask: the client's get (selector, expect, payload) -> (answers, errors)."""
    tiles, page = [], 0
    while True:
        q = MapTileQuery(stream=stream, ix_min=ix_min, ix_max=ix_max, iy_min=iy_min, iy_max=iy_max, page=page)
        out, errs = ask(keys.map_tile(stream, "*", "*"), MapTile, encode(q))
        tiles += out
        if not any(e.code == "truncated" for e in errs):
            return tiles, errs
        page += 1
