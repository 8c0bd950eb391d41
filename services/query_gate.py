"""Queries a client may have in work at once (`max_queries_per_client`), so one client's queries cannot starve the
others'.

A worker's queryable callbacks run on Zenoh's threads, and every query reaches a worker over its one link to the
router: ten looping `occvo/**` gets queued each legitimate tile query behind theirs. Here a callback only counts
the query against its client and hands it to a small pool of threads that answer it; a client with
`max_queries_per_client` queries in work gets an immediate `busy` reply naming the limit instead of a place in line.
Each queryable has its own gate and pool (a get on `occvo/**` is a query to each of them); a pool has one thread more
than one client may hold, so one client alone never takes every thread.

A client is the querying Zenoh session named by the query's source info (so querying a victim's stream name does not
use up the victim's budget), else the stream id's prefix before its first '.'; every query whose
stream chunk has a wildcard (`occvo/**`, `occvo/cam*/map/info`) counts as one client, `*`, allowed
`max_wildcard_queries` in work: such queries cost the most (a page of tiles of every stream), and a querier could
otherwise name a new prefix for each. With one wildcard query in work instead of two, a tile query's p50 / p99 beside
ten looping `occvo/**` gets was 9 / 22-57 ms instead of 10-15 / 45-66 ms (three runs each)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import zenoh

from occvo_schemas import keys
from occvo_services.limits import client_of

MAX_QUEUED = 64  # queries in work or waiting for a thread, all clients together; beyond, busy


def query_client(key: str, query: zenoh.Query | None = None, identity: str = "session") -> str:
    """Whose budget a query takes: `*` for a wildcard stream chunk; under `client_identity: "user"` (logins) the
    stream id's prefix, the login the access control lets query it (a source info is the querier's to write: a
    copied one would spend another's budget); else the querying session named by the query's source info
    (OccVOClient sets it; self-declared, as for frames), else the stream id's prefix."""
    stream = keys.stream_of(key)
    if stream == "*" or "*" in stream or "$" in stream:
        return "*"
    info = None if query is None or identity == "user" else query.source_info
    return client_of(stream) if info is None else str(info.source_id.zid)


class QueryGate:
    """Counts each client's queries in work and runs them on the pool; refuse(query, why) answers a refused one."""

    def __init__(
        self,
        per_client: int,
        wildcard: int,
        refuse: Callable[[zenoh.Query, str, str], None],
        name: str = "query",
        identity: str = "session",
    ):
        self.per_client, self.wildcard = per_client, wildcard
        self.identity = identity  # the worker's client_identity: whom a query's budget is taken from
        self.refuse = refuse
        self.pool = ThreadPoolExecutor(max(per_client, wildcard) + 1, thread_name_prefix=name)
        self._lock = threading.Lock()
        self.in_work: dict[str, int] = {}
        self._total = 0

    def wrap(self, handler: Callable[[zenoh.Query], None]) -> Callable[[zenoh.Query], None]:
        """A queryable callback that answers through the pool."""

        def callback(query: zenoh.Query) -> None:
            key = str(query.key_expr)
            client = query_client(key, query, self.identity)
            limit = self.wildcard if client == "*" else self.per_client
            with self._lock:
                held = self.in_work.get(client, 0)
                full = held >= limit or self._total >= MAX_QUEUED
                if not full:
                    self.in_work[client] = held + 1
                    self._total += 1
            if full:
                if held < limit:
                    why = f"{MAX_QUEUED} queries in work on this worker"
                elif client == "*":
                    why = f"max_wildcard_queries={limit} queries with a wildcard stream are in work"
                else:
                    why = f"client {client!r} has max_queries_per_client={limit} queries in work"
                return self.refuse(query, client, f"query {key} refused: {why}; ask again when one is answered")
            try:
                self.pool.submit(self._answer, handler, query, client)
            except RuntimeError:  # the pool is shut down: the worker is stopping
                self._done(client)

        return callback

    def _answer(self, handler: Callable[[zenoh.Query], None], query: zenoh.Query, client: str) -> None:
        try:
            handler(query)
        finally:
            self._done(client)
            query.drop()  # the final reply now, not when the object is collected

    def _done(self, client: str) -> None:
        with self._lock:
            self._total -= 1
            left = self.in_work[client] - 1
            if left:
                self.in_work[client] = left
            else:
                del self.in_work[client]

    def close(self) -> None:
        self.pool.shutdown(wait=True)
